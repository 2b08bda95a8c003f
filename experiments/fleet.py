"""The fleet file of a testbed run: every endpoint is a testbed address, shared memory off.

The registry (with its embedded router) listens on the `registry` host; each cloud daemon runs on
the host of the same name and the robot `robot-1` on the `robot` host; every peer listens on its
own host's address, so gossip tells the others where to reach it and data flows robot <->
deployment directly, over the links that `tc` shapes. Shared memory is off (it would bypass the
links) and multicast scouting is off (`common.session` always turns it off): peers meet through
the explicit registry endpoint only.

With `tls` (`elasticfog bench ... --tls`) the fleet is secured as `elasticfog init --tls` secures
one (`common.fleet_tls`): a fleet CA and a certificate per host in `certs/` beside the fleet
file, each carrying its host's testbed address as an IP SAN (Zenoh checks it), every endpoint
`tls/`, mutual TLS and the access control on. The observer on the `bench` host shows the
registry's certificate (it reads the views and injects faults through ctl keys, which only the
registry may query), so that certificate carries the bench host's address too.
"""

from __future__ import annotations

import copy
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from common.config import FleetConfig, fleet_from_dict
from common.defaults import DEFAULT_CAMERA_SOURCE
from common.fleet_tls import tls_settings, write_certs
from common.yaml_files import read_yaml
from deploy.local_fleet import merge_into

from .defaults import DEFAULT_INPUT_SHAPE, DEFAULT_MODEL

REGISTRY_HOST = "registry"
ROBOT_HOST = "robot"
ROBOT_ID = "robot-1"
REGISTRY_ID = "registry"
"""The registry's machine id (fleet.yaml's default): its certificate's common name."""
OBSERVER_HOST = "bench"
CLOUD_HOSTS = ("edge-1", "edge-2", "cloud-1", "cloud-2")
SERVICE = "vision"
REGISTRY_PORT = 7447
PEER_PORT = 7448
OBSERVER_PORT = 7449


@dataclass(frozen=True)
class PolicyVariant:
    """A bench policy name beyond the runtime's: the policy kind the robot runs (`--policy`),
    its parameters, and what else of the fleet file the robot reads otherwise."""

    kind: str
    params: Mapping[str, Any] = field(default_factory=dict)
    fleet: Mapping[str, Any] = field(default_factory=dict)
    """Merged into the robot's copy of the fleet file (nested mappings merge, other values
    replace), e.g. `fidelity: {video: true}`; the deployments read the fleet's own file."""


POLICY_VARIANTS: dict[str, PolicyVariant] = {
    # ElasticAction without hedged exploration: on a robot with a few % of a core, the hedged
    # local run and the offload's sending share that CPU and the learner sees the transfer slow.
    # Its periodic local timing (`robot_probe_frames`) stays on: without it a robot whose CPU
    # came back would never learn that computing locally got cheap again.
    "elastic-nohedge": PolicyVariant("elastic", {"hedge": False}),
    # ElasticAction over whole suffixes only, on a split made with segments (`bench nav`'s
    # `elastic` row, as it ran before segments were actions; `elastic-segments` is the default).
    "elastic-suffixes": PolicyVariant("elastic", {"segments": False}),
    # ElasticAction with h264 video among the camera image's codecs (docs/video.md): cut 0 may
    # cross as h264 where it meets the same fidelity bound as JPEG (measured at start).
    "elastic-h264": PolicyVariant("elastic", fleet={"fidelity": {"video": True}}),
    # The same with h264 the camera image's only lossy codec (`fidelity.codecs`; raw always
    # may cross): what elastic makes of h264 when no JPEG action is there to learn from first.
    "elastic-h264only": PolicyVariant(
        "elastic", fleet={"fidelity": {"video": True, "codecs": ["h264"]}}
    ),
}
"""Bench policy names beyond the runtime's: name -> its variant."""


@dataclass
class FleetSpec:
    """What a testbed run's fleet looks like; `fleet_dict` turns it into fleet.yaml's mapping."""

    fleet: str
    clouds: Sequence[str] = ("edge-1",)
    serving: str = "edge-1"
    model: str = DEFAULT_MODEL
    input_shape: Sequence[int] | None = DEFAULT_INPUT_SHAPE
    deadline_s: float = 10.0
    latency_bound: Mapping[str, Any] = field(
        default_factory=lambda: {"stat": "median", "seconds": 30.0, "window": 20}
    )
    policy: str = "elastic"
    fps: float | None = None
    lease_ms: int = 3000
    """Longer than a 64 KB Zenoh batch takes at 0.5 Mbit/s (1.1 s): a slow link is not dead."""
    robot_threads: int = 1
    cloud_threads: int = 1
    cloud_workers: int = 1
    services: Mapping[str, Mapping[str, Any]] | None = None
    """Several services (fleet.yaml's `services:`, name -> {model|handler, overrides}), written
    in place of the one-service form's `service`, `model` and `input_shape`; None: that form."""
    source: str = DEFAULT_CAMERA_SOURCE
    """The robot's frame source (a `common.source_spec` spec)."""
    changes: Mapping[str, Any] = field(default_factory=dict)
    """Merged into the mapping last (nested mappings merge, other values replace)."""


def endpoint(address: str, port: int, *, tls: bool = False) -> str:
    """A Zenoh endpoint: TCP, or TLS in a TLS fleet."""
    return f"{'tls' if tls else 'tcp'}/{address}:{port}"


def fleet_dict(
    spec: FleetSpec, addresses: Mapping[str, str], db: Path, *, tls: bool = False
) -> dict[str, Any]:
    """fleet.yaml's mapping for `spec` on a testbed whose hosts have `addresses`; with `tls`,
    TLS endpoints and the certificates of `cert_ips` (written by `write_fleet`)."""
    missing = [h for h in (REGISTRY_HOST, ROBOT_HOST, *spec.clouds) if h not in addresses]
    if missing:
        raise ValueError(f"the testbed has no host {', '.join(missing)}")
    if spec.serving not in spec.clouds:
        raise ValueError(f"serving deployment {spec.serving} is not one of {list(spec.clouds)}")
    registry = endpoint(addresses[REGISTRY_HOST], REGISTRY_PORT, tls=tls)
    machines: dict[str, Any] = {}
    for cloud in spec.clouds:
        machines[cloud] = {
            "role": "cloud",
            "listen": [endpoint(addresses[cloud], PEER_PORT, tls=tls)],
            "threads": spec.cloud_threads,
            "workers": spec.cloud_workers,
        }
    robot: dict[str, Any] = {
        "role": "robot",
        "listen": [endpoint(addresses[ROBOT_HOST], PEER_PORT, tls=tls)],
        "threads": spec.robot_threads,
        "source": spec.source,
    }
    if spec.fps is not None:
        robot["fps"] = spec.fps
    machines[ROBOT_ID] = robot
    initial: dict[str, Any] = {ROBOT_ID: "robot"}
    initial.update({c: "service" if c == spec.serving else "standby" for c in spec.clouds})
    data: dict[str, Any] = {
        "fleet": spec.fleet,
        "service": SERVICE,
        "model": spec.model,
        "services": {name: dict(svc) for name, svc in (spec.services or {}).items()},
        "registry": {
            "endpoint": registry,
            "listen": [registry],
            "embedded_router": True,
            "db": str(db),
        },
        "machines": machines,
        "initial_policy": initial,
        "latency_bound": dict(spec.latency_bound),
        "deadline_s": spec.deadline_s,
        "policy": {"kind": spec.policy},
        "zenoh": {"mode": "peer", "lease_ms": spec.lease_ms, "shared_memory": False},
    }
    if spec.services:
        del data["service"], data["model"]  # the services name their own
    else:
        del data["services"]
        if spec.input_shape is not None:
            data["input_shape"] = list(spec.input_shape)
    if tls:
        merge_into(data, tls_settings(REGISTRY_ID, machines))
    return merge_into(data, dict(spec.changes))


def cert_ips(spec: FleetSpec, addresses: Mapping[str, str]) -> dict[str, list[str]]:
    """Each host's testbed addresses, for its certificate's IP SANs: where it listens (the
    registry's also where the observer, showing its certificate, listens)."""
    ips = {REGISTRY_ID: [addresses[REGISTRY_HOST]], ROBOT_ID: [addresses[ROBOT_HOST]]}
    if OBSERVER_HOST in addresses:
        ips[REGISTRY_ID].append(addresses[OBSERVER_HOST])
    ips.update({cloud: [addresses[cloud]] for cloud in spec.clouds})
    return ips


def write_robot_variant(config: Path, policy: str) -> tuple[Path, str]:
    """For a POLICY_VARIANTS name: a copy of `config` whose policy is that variant (and with the
    variant's fleet changes), and the policy kind to pass to `elasticfog robot --policy`. Other
    names: `config` and the name."""
    variant = POLICY_VARIANTS.get(policy)
    if variant is None:
        return config, policy
    data = read_yaml(config)  # the user's fleet file: a key given twice is refused
    data["policy"] = {"kind": variant.kind, "params": copy.deepcopy(dict(variant.params))}
    merge_into(data, copy.deepcopy(dict(variant.fleet)))
    path = config.with_name(f"{config.stem}.{policy}.yaml")
    fleet_from_dict(data, source=path)
    path.write_text(yaml.safe_dump(data, sort_keys=False), encoding="utf-8")
    return path, variant.kind


def write_fleet(
    spec: FleetSpec, addresses: Mapping[str, str], directory: Path, *, tls: bool = False
) -> tuple[Path, FleetConfig]:
    """Write `directory/<fleet>.yaml`, check it loads, return its path and the loaded config.
    With `tls`, a new CA and the hosts' certificates in `directory/certs/` first."""
    directory.mkdir(parents=True, exist_ok=True)
    path = directory / f"{spec.fleet}.yaml"
    data = fleet_dict(spec, addresses, directory / f"{spec.fleet}.rib.sqlite", tls=tls)
    if tls:
        ips = cert_ips(spec, addresses)
        write_certs(directory, list(ips), fleet=spec.fleet, ips=ips, force=True)
    cfg = fleet_from_dict(data, source=path)  # a bad spec fails here, naming the field
    header = (
        "# Written by `elasticfog bench` for one run on the namespace testbed: every endpoint is\n"
        "# a testbed address; shared memory is off so that tc shaping applies.\n"
    )
    if tls:
        header += "# Mutual TLS and access control on every link; certificates in certs/.\n"
    path.write_text(header + yaml.safe_dump(data, sort_keys=False), encoding="utf-8")
    return path, cfg

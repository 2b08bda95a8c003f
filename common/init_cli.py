"""`elasticfog init DIR`: write a commented, single-host fleet.yaml to start from.

The file describes a registry listening on 127.0.0.1:PORT, two cloud deployments (`edge-1` in
service, `edge-2` standby) and robots `robot-1` ... `robot-N` (`--robots N`, default 1), with a
latency bound and a deadline. It is checked with `load_fleet` before it is written, so what
`init` writes always loads.

With `--tls` every link is mutual TLS: `elasticfog certs`' files go to DIR/certs/ (a fleet CA, one
certificate per host carrying 127.0.0.1 and localhost, and the read-only `cli` one), endpoints
are `tls/...`, and the access control generated from the file (common/acl.py) is on, so the
fleet is ready to run as it is.
"""

from __future__ import annotations

import json
from pathlib import Path

import typer

from common.defaults import DEFAULT_FLEET, DEFAULT_REGISTRY_PORT
from common.errors import UserError
from common.fleet_tls import CERTS_DIR, ca_path, host_tls, write_certs

FLEET_FILE = "fleet.yaml"
REGISTRY_ID = "registry"
DEFAULT_MODEL = "zoo:resnet"
DEFAULT_SERVICE = "vision"
CLOUD_IDS = ("edge-1", "edge-2")
MAX_ROBOTS = 1000

# Values are JSON-quoted (valid YAML), so a fleet named `yes` or `123` stays a string.
TEMPLATE = """\
# elasticfog fleet, written by `elasticfog init`: everything on this host (loopback).
# Start each line in its own terminal, in this folder:
#   elasticfog registry --config fleet.yaml
#   elasticfog cloud --config fleet.yaml --id edge-1
#   elasticfog cloud --config fleet.yaml --id edge-2
{robot_lines}
# Unknown keys are errors. Relative paths are relative to this file.

# Fleet name: every Zenoh key of this fleet starts with ef/<fleet>/.
fleet: {fleet}
# The service robots call; its anycast key is ef/<fleet>/svc/<service>/<robot>/infer.
service: {service}
# The ONNX model: zoo:<name> (built from code, see `elasticfog model zoo list`) or a path.
model: {model}
# Candidate cuts: at most this many tensors cross a cut (null names = every cut found).
cuts:
  max_cut_tensors: 2
  names: null
# anycast: one deployment serves each robot. round_robin: a pool of deployments serves it
# together, each frame computed by one member in turn (robots need max_in_flight > 1 to overlap
# them); pool_size: deployments per pool (left out: every live one).
dispatch:
  mode: anycast

registry:
  # Where every daemon and CLI connects to meet the fleet. For several hosts, use an address
  # the other hosts can reach, and listen on it.
  endpoint: {endpoint}
  # The registry embeds a Zenoh router listening here.
  listen: [{endpoint}]
  embedded_router: true{registry_tls}
  # The routing information base (sqlite); default: <fleet>.rib.sqlite next to this file.
  # db: rib.sqlite
  # Prometheus /metrics of the registry (docs/metrics.md); any machine takes the same key.
  # metrics: {{port: 9400}}

# Machines by id. Peers talk to each other directly: each listens on an endpoint the others can
# reach (port 0: any free port, announced to the others through the registry's router).
machines:
{machines}
# Who serves whom at start (FogROS2-LS): exactly one cloud in service per robot.
initial_policy:
{robot_policy}  edge-1: service
  edge-2: standby

# The scheduler keeps <stat> of the last <window> frames' latencies under <seconds>; a violation
# held for hysteresis_s moves the robot to a deployment predicted to meet the bound.
latency_bound:
  stat: median          # median | mean | p95 | max | stddev
  seconds: 0.3
  window: 20
  hysteresis_s: 1.0
  better_margin: 0.2    # move a satisfied robot only for a deployment 20% better

# Past this, the robot finishes the frame itself (no frame is ever lost).
deadline_s: 0.5

# The split policy: elastic (ElasticAction), robot, cloud, static:<k>, neurosurgeon, ans.
policy:
  kind: elastic
  params: {{}}

# What a policy minimises per frame (weights).
objective:
  latency: 1.0
  cpu: 0.0
  energy: 0.0
  bytes: 0.0

zenoh:
  mode: peer
  lease_ms: 1000          # a silent peer is dropped after this
  shared_memory: true     # between processes of this host
{zenoh_tls}"""

CLOUD_TEMPLATE = """\
  {id}:
    role: cloud
    listen: [{proto}/127.0.0.1:0]
    workers: 1        # inference workers
    queue: 4          # requests waiting for a worker before answering "busy"
{fault}{tls}"""
FAULT_LINE = (
    "    fault: {delay_ms: 0, drop: 0, stall: false}   # fault injection at start (tests)\n"
)
ROBOT_TEMPLATE = """\
  {id}:
    role: robot
    listen: [{proto}/127.0.0.1:0]
    # Frame source (docs/robot.md): synthetic, photo[:NAME], video:PATH, bag:PATH[:TOPIC] (a
    # rosbag2 recording), camera:0 or camera:/dev/video0, zenoh (frames an application
    # publishes), ros2:TOPIC (a ROS 2 image topic), stereo:world (a two-image model).
    source: synthetic
    fps: 10
    # uplink_mbit: 2    # pace the uplink in the application (single-host emulation)
{tls}"""
HOST_TLS = "    tls: {{cert: {cert}, key: {key}}}\n"
ZENOH_TLS = """\
  # Mutual TLS on every link: each host shows its own certificate (common name = its id,
  # made by `elasticfog certs`) and accepts only certificates signed by this CA.
  tls:
    ca: {ca}
    mtls: true
  # Each host may touch only its own keys (generated from this file, see docs/security.md).
  access_control: true

# The views CLI (`elasticfog routes --config fleet.yaml`) uses this read-only certificate.
cli:
  tls: {{cert: {cli_cert}, key: {cli_key}}}
"""


def robot_ids(robots: int) -> list[str]:
    """`robot-1` ... `robot-N`."""
    return [f"robot-{i}" for i in range(1, robots + 1)]


def render_fleet(
    *,
    port: int = DEFAULT_REGISTRY_PORT,
    fleet: str = DEFAULT_FLEET,
    model: str = DEFAULT_MODEL,
    service: str = DEFAULT_SERVICE,
    robots: int = 1,
    tls: bool = False,
) -> str:
    """The text of a single-host fleet.yaml (with `tls`: the settings of
    `common.fleet_tls.tls_settings`, certificates expected in certs/)."""
    proto = "tls" if tls else "tcp"

    def own_tls(host: str) -> str:
        return HOST_TLS.format(**host_tls(host)) if tls else ""

    machines = [
        CLOUD_TEMPLATE.format(
            id=cloud, proto=proto, fault=FAULT_LINE if i == 0 else "", tls=own_tls(cloud)
        )
        for i, cloud in enumerate(CLOUD_IDS)
    ]
    robot_list = robot_ids(robots)
    machines += [ROBOT_TEMPLATE.format(id=r, proto=proto, tls=own_tls(r)) for r in robot_list]
    return TEMPLATE.format(
        fleet=json.dumps(fleet),
        service=json.dumps(service),
        model=json.dumps(model),
        endpoint=f"{proto}/127.0.0.1:{port}",
        robot_lines="\n".join(
            f"#   elasticfog robot --config fleet.yaml --id {r} --frames 100" for r in robot_list
        ),
        registry_tls="\n  " + own_tls(REGISTRY_ID).strip() if tls else "",
        machines="".join(machines),
        robot_policy="".join(f"  {r}: robot\n" for r in robot_list),
        zenoh_tls=_zenoh_tls() if tls else "",
    )


def _zenoh_tls() -> str:
    cli = host_tls("cli")
    return ZENOH_TLS.format(ca=ca_path(), cli_cert=cli["cert"], cli_key=cli["key"])


def write_fleet(
    directory: Path,
    *,
    port: int = DEFAULT_REGISTRY_PORT,
    fleet: str = DEFAULT_FLEET,
    model: str = DEFAULT_MODEL,
    force: bool = False,
    robots: int = 1,
    tls: bool = False,
) -> Path:
    """Write DIR/fleet.yaml (creating DIR) and return its path; with `tls`, DIR/certs/ too (a
    fleet CA and a certificate per host). UserError on bad input or if a file exists and `force`
    is false."""
    # Heavy imports (pydantic, the wire codec, cryptography) where the command runs:
    # `elasticfog --help` must stay fast.
    from common.config import ZOO_PREFIX, fleet_from_dict
    from common.keys import validate_id
    from common.yaml_files import parse_yaml

    validate_id(fleet, "fleet name")
    if not 1 <= port <= 65535:
        raise UserError(f"--port {port}: expected a TCP port in 1..65535")
    if not 1 <= robots <= MAX_ROBOTS:
        raise UserError(f"--robots {robots}: expected 1..{MAX_ROBOTS}")
    if model.startswith(ZOO_PREFIX):
        validate_id(model[len(ZOO_PREFIX) :], "zoo model name")
    else:
        model_file = Path(model).expanduser().resolve()
        if not model_file.is_file():
            raise UserError(f"--model {model}: no such file (or use zoo:NAME)")
        model = str(model_file)
    if directory.exists() and not directory.is_dir():
        raise UserError(f"{directory}: exists and is not a directory")
    target = directory / FLEET_FILE
    if target.exists() and not force:
        raise UserError(f"{target}: already exists; use --force to overwrite it")
    text = render_fleet(port=port, fleet=fleet, model=model, robots=robots, tls=tls)
    fleet_from_dict(parse_yaml(text, str(target)), source=target)  # what we write must load
    if tls:
        write_certs(
            directory, [REGISTRY_ID, *CLOUD_IDS, *robot_ids(robots)], fleet=fleet, force=force
        )
    try:
        directory.mkdir(parents=True, exist_ok=True)
        target.write_text(text, encoding="utf-8")
    except OSError as exc:
        raise UserError(f"{target}: cannot write: {exc.strerror or exc}") from None
    return target


def init(
    directory: Path = typer.Argument(..., metavar="DIR", help="Folder to write fleet.yaml into."),
    port: int = typer.Option(
        DEFAULT_REGISTRY_PORT, "--port", help="Port the registry listens on (127.0.0.1)."
    ),
    fleet: str = typer.Option(DEFAULT_FLEET, "--fleet", help="Fleet name (in every key)."),
    model: str = typer.Option(DEFAULT_MODEL, "--model", help="zoo:NAME or an ONNX file."),
    robots: int = typer.Option(1, "--robots", help="Robots robot-1 ... robot-N."),
    tls: bool = typer.Option(
        False,
        "--tls",
        help="Mutual TLS and access control on every link, certificates in DIR/certs/.",
    ),
    force: bool = typer.Option(
        False, "--force", help="Overwrite an existing fleet.yaml (and certificates)."
    ),
) -> None:
    """Write a commented single-host fleet.yaml: a registry, edge-1 (service), edge-2 (standby)
    and robot-1 ... robot-N."""
    try:
        target = write_fleet(
            directory, port=port, fleet=fleet, model=model, force=force, robots=robots, tls=tls
        )
    except UserError as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(exc.exit_code) from None
    typer.echo(f"wrote {target}")
    if tls:
        typer.echo(f"wrote certificates in {directory / CERTS_DIR} (see `elasticfog certs show`)")
    typer.echo(f"next: elasticfog registry --config {target}")


def register(app: typer.Typer) -> None:
    """Add `elasticfog init` to the root app."""
    app.command("init")(init)

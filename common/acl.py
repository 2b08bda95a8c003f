"""Zenoh access control generated from the fleet file, in one place.

Every session of a TLS fleet (each daemon's and the registry's router) carries the same
`access_control` section, built here from fleet.yaml. Zenoh applies it on each link: a message
that another host sends us (ingress) or that we send it (egress) is allowed only when a rule of
that host's subject allows its kind on a key expression that includes the message's key. Hosts
are subjects by the common name of their certificate (mutual TLS), which `elasticfog certs`
sets to the machine id; a certificate whose name is not a host of the fleet matches no subject
and gets the default, deny.

What each host may send (ingress on every other host), with keys from `common.keys`:

- registry: everything under `ef/<fleet>/**`. It is the fleet's router, so it relays the other
  hosts' declarations and, for clients, their data; those were filtered when they entered it.
- cloud `<d>`: declare and answer the service queryables of its fleet and service
  (`svc/<service>/*/infer`) and its own pool member keys (`svc/<service>/*/infer/<d>`), its own
  `dep/<d>/{probe,ctl}`; its own liveliness token; query the
  registry's drain key; follow the fleet's liveliness tokens.
- robot `<r>`: query its own service key and pool member keys, the registry's register/reroute
  keys and the deployments' probes (`dep/*/probe`, how it measures them); publish its own
  telemetry, probe reports and results (`out/<r>`); subscribe to its own route and frames
  (`in/<r>`), and put frames there (an application on the robot's host, with its certificate);
  its own liveliness token; follow liveliness tokens.
- cli: query the registry's views (`rib/*`) and follow the robots' results (`out/*`); nothing
  else.

Egress is open within the fleet's prefix for every known host: what a host can receive follows
from what it may declare and query, which every other host checks on ingress (a robot that may
not subscribe to another's route never gets it sent). Only the registry may query `ctl` keys and
publish routes, since no other subject has a rule for them.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from common import keys
from common.config import CLI_IDENTITY
from common.keys import Role

if TYPE_CHECKING:
    from common.config import FleetConfig


class Message(str, enum.Enum):
    """Zenoh's ACL message kinds (zenoh-config `AclMessage`, snake_case on the wire)."""

    PUT = "put"
    DELETE = "delete"
    DECLARE_SUBSCRIBER = "declare_subscriber"
    QUERY = "query"
    DECLARE_QUERYABLE = "declare_queryable"
    REPLY = "reply"
    LIVELINESS_TOKEN = "liveliness_token"
    DECLARE_LIVELINESS_SUBSCRIBER = "declare_liveliness_subscriber"
    LIVELINESS_QUERY = "liveliness_query"


ALL_MESSAGES = tuple(Message)
FOLLOW_LIVELINESS = (Message.DECLARE_LIVELINESS_SUBSCRIBER, Message.LIVELINESS_QUERY)


@dataclass(frozen=True)
class Grant:
    """One allowance: a host may send these message kinds on these key expressions."""

    messages: tuple[Message, ...]
    key_exprs: tuple[str, ...]
    why: str


def registry_grants(cfg: FleetConfig) -> list[Grant]:
    """The registry (and its router): everything within the fleet."""
    return [Grant(ALL_MESSAGES, (keys.fleet_all(cfg.fleet),), "the fleet's router and RIB")]


def cloud_grants(cfg: FleetConfig, deployment: str) -> list[Grant]:
    """A cloud deployment: the service keys of the services it serves and its own probe/ctl."""
    fleet = cfg.fleet
    own = (keys.dep_probe(fleet, deployment), keys.dep_ctl(fleet, deployment))
    served = cfg.services_of(deployment)
    service = [keys.svc_infer_all(fleet, name) for name in served]
    member = [keys.svc_infer_at_all(fleet, name, deployment) for name in served]
    return [
        Grant(
            (Message.DECLARE_QUERYABLE, Message.REPLY),
            (*service, *member, *own),
            "serve its fleet's service (and its own pool member keys); answer its own probe "
            "and ctl",
        ),
        Grant(
            (Message.LIVELINESS_TOKEN,),
            (keys.alive_deployment(fleet, deployment),),
            "its own token",
        ),
        Grant((Message.QUERY,), (keys.reg_drain(fleet),), "ask the registry to drain it"),
        Grant(FOLLOW_LIVELINESS, (keys.alive_all(fleet),), "follow the fleet's membership"),
    ]


def robot_grants(cfg: FleetConfig, robot: str) -> list[Grant]:
    """A robot: its own service keys (one per service it uses), telemetry, route and token;
    the registry's requests."""
    fleet = cfg.fleet
    return [
        Grant(
            (Message.QUERY,),
            (
                *(keys.svc_infer(fleet, name, robot) for name in cfg.services_of(robot)),
                *(keys.svc_infer_pool(fleet, name, robot) for name in cfg.services_of(robot)),
                keys.reg_register(fleet),
                keys.reg_reroute(fleet),
                keys.dep_probe_all(fleet),
            ),
            "its own service and pool member keys, register/reroute, probe the deployments",
        ),
        Grant(
            (Message.PUT,),
            (
                keys.tele(fleet, robot),
                keys.tele_probe(fleet, robot),
                keys.results_out(fleet, robot),
                keys.frames_in(fleet, robot),
            ),
            "its own telemetry, probe reports and results; frames to itself (an application "
            "on the robot, with its certificate)",
        ),
        Grant(
            (Message.DECLARE_SUBSCRIBER,),
            (keys.route(fleet, robot), keys.frames_in(fleet, robot)),
            "its own route and frames in",
        ),
        Grant((Message.LIVELINESS_TOKEN,), (keys.alive_robot(fleet, robot),), "its own token"),
        Grant(FOLLOW_LIVELINESS, (keys.alive_all(fleet),), "follow the fleet's membership"),
    ]


def cli_grants(cfg: FleetConfig) -> list[Grant]:
    """The read-only CLI certificate: the registry's views."""
    return [
        Grant((Message.QUERY,), (keys.rib_all(cfg.fleet),), "read the RIB views"),
        Grant(
            (Message.DECLARE_SUBSCRIBER,),
            (keys.results_out_all(cfg.fleet),),
            "follow the robots' results (`elasticfog results`)",
        ),
    ]


def grants(cfg: FleetConfig) -> dict[str, list[Grant]]:
    """What each subject (certificate common name) may send, in file order."""
    out: dict[str, list[Grant]] = {cfg.registry.id: registry_grants(cfg)}
    for machine_id, machine in cfg.machines.items():
        if machine.role is Role.CLOUD:
            out[machine_id] = cloud_grants(cfg, machine_id)
        else:
            out[machine_id] = robot_grants(cfg, machine_id)
    out[CLI_IDENTITY] = cli_grants(cfg)
    return out


def _rule(
    rule_id: str, messages: tuple[Message, ...], key_exprs: tuple[str, ...], flow: str
) -> Any:
    return {
        "id": rule_id,
        "permission": "allow",
        "flows": [flow],
        "messages": [m.value for m in messages],
        "key_exprs": list(key_exprs),
    }


def access_control(cfg: FleetConfig) -> dict[str, Any]:
    """Zenoh's `access_control` section for every session of this fleet (default deny)."""
    rules: list[dict[str, Any]] = []
    subjects: list[dict[str, Any]] = []
    policies: list[dict[str, Any]] = []
    egress_keys = (keys.fleet_all(cfg.fleet),)
    for subject, allowed in grants(cfg).items():
        subject_id = f"host:{subject}"
        rule_ids = []
        for index, grant in enumerate(allowed):
            rule_id = f"{subject}:send:{index}"
            rules.append(_rule(rule_id, grant.messages, grant.key_exprs, "ingress"))
            rule_ids.append(rule_id)
        rule_id = f"{subject}:receive"
        rules.append(_rule(rule_id, ALL_MESSAGES, egress_keys, "egress"))
        rule_ids.append(rule_id)
        subjects.append({"id": subject_id, "cert_common_names": [subject]})
        policies.append({"id": f"policy:{subject}", "rules": rule_ids, "subjects": [subject_id]})
    return {
        "enabled": True,
        "default_permission": "deny",
        "rules": rules,
        "subjects": subjects,
        "policies": policies,
    }


def table(cfg: FleetConfig) -> list[tuple[str, str, str, str]]:
    """(subject, messages, key expressions, why) rows: the ACL as docs/security.md shows it."""
    rows = []
    for subject, allowed in grants(cfg).items():
        for grant in allowed:
            rows.append(
                (
                    subject,
                    ", ".join(m.value for m in grant.messages),
                    ", ".join(grant.key_exprs),
                    grant.why,
                )
            )
    return rows

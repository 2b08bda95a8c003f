"""Every Zenoh key expression of the runtime, built in one place.

The key space is a public contract (other tools and languages talk to these keys), documented in
docs/keyspace.md with who declares and who queries each key. Everything lives under `ef/<fleet>/`.
No other module formats a key with an f-string: call the function for the key instead, so a change
of layout is one edit here and a reader can find every user of a key by its function name.

Ids (fleet, service, machine and robot names) are single key chunks: they may not be empty and may
not contain '/', or the Zenoh wildcard and selector characters '*', '$', '#', '?'. Whitespace and
control characters are refused too: they make keys that cannot be typed on a command line.
"""

from __future__ import annotations

import enum
import re
from dataclasses import dataclass

from common.defaults import DEFAULT_FLEET as DEFAULT_FLEET  # re-exported
from common.errors import UserError

ROOT = "ef"
MAX_ID_CHARS = 128
FORBIDDEN_ID_CHARS = "/*$#?"

# The read-only views of the routing information base, each a queryable of the registry.
RIB_VIEWS = ("deployments", "robots", "routes", "events", "profiles")


class Role(str, enum.Enum):
    """The roles of a fleet's members: the chunk after `alive/` of their liveliness tokens, a
    machine's `role` in the fleet file (cloud, robot) and a `RegisterRequest`'s (cloud, robot).
    The one spelling of them; a member formats as its value (`f"alive/{role}"`), as a
    `StrEnum`'s would (which Python 3.10 lacks)."""

    REGISTRY = "registry"
    CLOUD = "cloud"
    ROBOT = "robot"

    def __str__(self) -> str:
        return self.value

    def __format__(self, spec: str) -> str:
        return format(self.value, spec)


# Liveliness roles: the chunk after `alive/`.
ROLES = tuple(role.value for role in Role)
# The roles a machine of the fleet file has, and a daemon registers with (the registry is not one).
MACHINE_ROLES = (Role.CLOUD, Role.ROBOT)

_BAD_ID = re.compile(r"[/*$#?\s\x00-\x1f\x7f]")


class InvalidIdError(UserError, ValueError):
    """An id that cannot be a key chunk. A ValueError too, so pydantic validators report it."""


def validate_id(value: object, what: str = "id") -> str:
    """Return `value` if it can be used as one key chunk, else raise InvalidIdError naming it."""
    if not isinstance(value, str):
        raise InvalidIdError(f"{what} must be a string, got {type(value).__name__}")
    if not value:
        raise InvalidIdError(f"{what} must not be empty")
    if len(value) > MAX_ID_CHARS:
        raise InvalidIdError(f"{what} {value[:20]!r}... is longer than {MAX_ID_CHARS} characters")
    bad = _BAD_ID.search(value)
    if bad is not None:
        ch = bad.group()
        shown = repr(ch) if ch.isprintable() and not ch.isspace() else f"U+{ord(ch):04X}"
        raise InvalidIdError(
            f"{what} {value!r} contains {shown}; ids may not contain '/', '*', '$', '#', '?', "
            "whitespace or control characters"
        )
    return value


def _join(*chunks: str) -> str:
    return "/".join(chunks)


def prefix(fleet: str) -> str:
    """`ef/<fleet>`: the root of one fleet's keys."""
    return _join(ROOT, validate_id(fleet, "fleet name"))


def fleet_all(fleet: str) -> str:
    """`ef/<fleet>/**`: every key of one fleet (the access control's widest grant)."""
    return _join(prefix(fleet), "**")


# -- rib: the registry's read-only views -----------------------------------------------------------
def rib(fleet: str, view: str) -> str:
    """`ef/<fleet>/rib/<view>`: one view of the routing information base (see RIB_VIEWS)."""
    if view not in RIB_VIEWS:
        raise InvalidIdError(f"unknown RIB view {view!r}; known: {', '.join(RIB_VIEWS)}")
    return _join(prefix(fleet), "rib", view)


def rib_deployments(fleet: str) -> str:
    """`ef/<fleet>/rib/deployments`."""
    return rib(fleet, "deployments")


def rib_robots(fleet: str) -> str:
    """`ef/<fleet>/rib/robots`."""
    return rib(fleet, "robots")


def rib_routes(fleet: str) -> str:
    """`ef/<fleet>/rib/routes`."""
    return rib(fleet, "routes")


def rib_events(fleet: str) -> str:
    """`ef/<fleet>/rib/events`."""
    return rib(fleet, "events")


def rib_profiles(fleet: str) -> str:
    """`ef/<fleet>/rib/profiles` (extension): robot x deployment latency profiles."""
    return rib(fleet, "profiles")


def rib_all(fleet: str) -> str:
    """`ef/<fleet>/rib/*`: every RIB view (a registry may declare one queryable for all)."""
    return _join(prefix(fleet), "rib", "*")


# -- reg: requests to the registry (extension) -----------------------------------------------------
def reg_register(fleet: str) -> str:
    """`ef/<fleet>/reg/register`: a daemon announces its protocol version and capabilities."""
    return _join(prefix(fleet), "reg", "register")


def reg_reroute(fleet: str) -> str:
    """`ef/<fleet>/reg/reroute`: a robot asks for a new route (e.g. after consecutive timeouts)."""
    return _join(prefix(fleet), "reg", "reroute")


def reg_drain(fleet: str) -> str:
    """`ef/<fleet>/reg/drain`: a deployment about to stop asks to have its robots moved first."""
    return _join(prefix(fleet), "reg", "drain")


# -- alive: liveliness tokens ----------------------------------------------------------------------
def alive(fleet: str, role: str, machine: str) -> str:
    """`ef/<fleet>/alive/<role>/<id>` for role in ROLES."""
    if role not in ROLES:
        raise InvalidIdError(f"unknown role {role!r}; known: {', '.join(ROLES)}")
    return _join(prefix(fleet), "alive", role, validate_id(machine, f"{role} id"))


def alive_registry(fleet: str, registry: str) -> str:
    """`ef/<fleet>/alive/registry/<id>`."""
    return alive(fleet, "registry", registry)


def alive_deployment(fleet: str, deployment: str) -> str:
    """`ef/<fleet>/alive/cloud/<deployment>`."""
    return alive(fleet, "cloud", deployment)


def alive_robot(fleet: str, robot: str) -> str:
    """`ef/<fleet>/alive/robot/<robot>`."""
    return alive(fleet, "robot", robot)


def alive_all(fleet: str) -> str:
    """`ef/<fleet>/alive/**`: every token of the fleet (membership seed and subscription)."""
    return _join(prefix(fleet), "alive", "**")


def alive_registries(fleet: str) -> str:
    """`ef/<fleet>/alive/registry/*`."""
    return _join(prefix(fleet), "alive", "registry", "*")


def alive_deployments(fleet: str) -> str:
    """`ef/<fleet>/alive/cloud/*`."""
    return _join(prefix(fleet), "alive", "cloud", "*")


def alive_robots(fleet: str) -> str:
    """`ef/<fleet>/alive/robot/*`."""
    return _join(prefix(fleet), "alive", "robot", "*")


# -- svc: the anycast service key ------------------------------------------------------------------
def svc_infer(fleet: str, service: str, robot: str) -> str:
    """`ef/<fleet>/svc/<service>/<robot>/infer`: declared only by the deployment in service."""
    service = validate_id(service, "service name")
    return _join(prefix(fleet), "svc", service, validate_id(robot, "robot id"), "infer")


def svc_infer_all(fleet: str, service: str) -> str:
    """`ef/<fleet>/svc/<service>/*/infer`: the service key of every robot."""
    return _join(prefix(fleet), "svc", validate_id(service, "service name"), "*", "infer")


def svc_infer_at(fleet: str, service: str, robot: str, deployment: str) -> str:
    """`ef/<fleet>/svc/<service>/<robot>/infer/<deployment>`: one member of the robot's round-robin
    pool (`dispatch: round_robin`). Declared beside the service key by every deployment in service
    for the robot, so a robot addresses one member and each frame is computed exactly once."""
    return _join(svc_infer(fleet, service, robot), validate_id(deployment, "deployment id"))


def svc_infer_pool(fleet: str, service: str, robot: str) -> str:
    """`ef/<fleet>/svc/<service>/<robot>/infer/*`: the member keys of one robot's pool."""
    return _join(svc_infer(fleet, service, robot), "*")


def svc_infer_at_all(fleet: str, service: str, deployment: str) -> str:
    """`ef/<fleet>/svc/<service>/*/infer/<deployment>`: one deployment's member key of every
    robot."""
    return _join(svc_infer_all(fleet, service), validate_id(deployment, "deployment id"))


# -- dep: per-deployment probe and control ---------------------------------------------------------
def dep_probe(fleet: str, deployment: str) -> str:
    """`ef/<fleet>/dep/<deployment>/probe`: answered in every state."""
    return _join(prefix(fleet), "dep", validate_id(deployment, "deployment id"), "probe")


def dep_ctl(fleet: str, deployment: str) -> str:
    """`ef/<fleet>/dep/<deployment>/ctl`: state control and fault injection."""
    return _join(prefix(fleet), "dep", validate_id(deployment, "deployment id"), "ctl")


def dep_probe_all(fleet: str) -> str:
    """`ef/<fleet>/dep/*/probe`."""
    return _join(prefix(fleet), "dep", "*", "probe")


# -- tele: what robots publish ---------------------------------------------------------------------
def tele(fleet: str, robot: str) -> str:
    """`ef/<fleet>/tele/<robot>`: one telemetry record per frame."""
    return _join(prefix(fleet), "tele", validate_id(robot, "robot id"))


def tele_all(fleet: str) -> str:
    """`ef/<fleet>/tele/*`: per-frame telemetry of every robot (not the probe reports)."""
    return _join(prefix(fleet), "tele", "*")


def tele_probe(fleet: str, robot: str) -> str:
    """`ef/<fleet>/tele/<robot>/probe` (extension): the robot's probe reports."""
    return _join(prefix(fleet), "tele", validate_id(robot, "robot id"), "probe")


def tele_probe_all(fleet: str) -> str:
    """`ef/<fleet>/tele/*/probe`."""
    return _join(prefix(fleet), "tele", "*", "probe")


# -- route: what the registry publishes ------------------------------------------------------------
def route(fleet: str, robot: str) -> str:
    """`ef/<fleet>/route/<robot>`: epoch-numbered route changes for one robot."""
    return _join(prefix(fleet), "route", validate_id(robot, "robot id"))


def route_all(fleet: str) -> str:
    """`ef/<fleet>/route/*`."""
    return _join(prefix(fleet), "route", "*")


# -- out/in: results to applications, frames from them ---------------------------------------------
def results_out(fleet: str, robot: str) -> str:
    """`ef/<fleet>/out/<robot>`: each applied frame's result, published by the robot."""
    return _join(prefix(fleet), "out", validate_id(robot, "robot id"))


def results_out_all(fleet: str) -> str:
    """`ef/<fleet>/out/*`: the results of every robot."""
    return _join(prefix(fleet), "out", "*")


def frames_in(fleet: str, robot: str) -> str:
    """`ef/<fleet>/in/<robot>`: frames an application sends the robot (its `zenoh` source)."""
    return _join(prefix(fleet), "in", validate_id(robot, "robot id"))


def frames_in_all(fleet: str) -> str:
    """`ef/<fleet>/in/*`: the frames sent to every robot."""
    return _join(prefix(fleet), "in", "*")


# -- parsing ---------------------------------------------------------------------------------------
class KeyKind(str, enum.Enum):
    """What a concrete key is, as returned by parse_key."""

    RIB = "rib"
    REG_REGISTER = "reg_register"
    REG_REROUTE = "reg_reroute"
    REG_DRAIN = "reg_drain"
    ALIVE = "alive"
    SVC_INFER = "svc_infer"
    SVC_INFER_AT = "svc_infer_at"
    DEP_PROBE = "dep_probe"
    DEP_CTL = "dep_ctl"
    TELE = "tele"
    TELE_PROBE = "tele_probe"
    ROUTE = "route"
    RESULTS_OUT = "results_out"
    FRAMES_IN = "frames_in"


@dataclass(frozen=True)
class KeyParts:
    """A concrete key taken apart.

    `id` is the machine the key is about (deployment, robot or registry); `role` is set for
    liveliness keys, `service` for service keys, `view` for RIB keys; `member` is the deployment
    of a pool member key (`id` its robot).
    """

    fleet: str
    kind: KeyKind
    id: str | None = None
    role: str | None = None
    service: str | None = None
    view: str | None = None
    member: str | None = None


def parse_key(key: str) -> KeyParts | None:
    """Take a concrete key of this key space apart; None when it is not one of ours."""
    chunks = str(key).split("/")
    if len(chunks) < 3 or chunks[0] != ROOT:
        return None
    try:
        for chunk in chunks[1:]:
            validate_id(chunk)
    except InvalidIdError:
        return None
    fleet, area, rest = chunks[1], chunks[2], chunks[3:]
    match area, rest:
        case "rib", [view] if view in RIB_VIEWS:
            return KeyParts(fleet, KeyKind.RIB, view=view)
        case "reg", ["register"]:
            return KeyParts(fleet, KeyKind.REG_REGISTER)
        case "reg", ["reroute"]:
            return KeyParts(fleet, KeyKind.REG_REROUTE)
        case "reg", ["drain"]:
            return KeyParts(fleet, KeyKind.REG_DRAIN)
        case "alive", [role, machine] if role in ROLES:
            return KeyParts(fleet, KeyKind.ALIVE, id=machine, role=role)
        case "svc", [service, robot, "infer"]:
            return KeyParts(fleet, KeyKind.SVC_INFER, id=robot, service=service)
        case "svc", [service, robot, "infer", member]:
            return KeyParts(fleet, KeyKind.SVC_INFER_AT, id=robot, service=service, member=member)
        case "dep", [deployment, "probe"]:
            return KeyParts(fleet, KeyKind.DEP_PROBE, id=deployment)
        case "dep", [deployment, "ctl"]:
            return KeyParts(fleet, KeyKind.DEP_CTL, id=deployment)
        case "tele", [robot]:
            return KeyParts(fleet, KeyKind.TELE, id=robot)
        case "tele", [robot, "probe"]:
            return KeyParts(fleet, KeyKind.TELE_PROBE, id=robot)
        case "route", [robot]:
            return KeyParts(fleet, KeyKind.ROUTE, id=robot)
        case "out", [robot]:
            return KeyParts(fleet, KeyKind.RESULTS_OUT, id=robot)
        case "in", [robot]:
            return KeyParts(fleet, KeyKind.FRAMES_IN, id=robot)
    return None

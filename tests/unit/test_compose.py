"""The docker-compose demo, checked statically (no Docker engine runs on the build machines).

Parses deploy/docker-compose.yml with PyYAML and checks what `docker compose up` would trip on:
the services, the build context and Dockerfile (and what it copies), mounted files, the robot's
NET_ADMIN, and that every command and healthcheck is a real `elasticfog` command line: the
subcommands and options are parsed by the CLI's own click commands (`make_context`, which checks
names, types and required options without running anything), with container paths mapped back
to the files mounted there. The `--id`s must be machines of the mounted fleet file, with the role
the daemon expects, and the hosts must be the namespace testbed's, so one topology runs in both.
"""

from __future__ import annotations

import posixpath
import re
import shlex
import sys
from pathlib import Path
from typing import Any

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - Python 3.10
    import tomli as tomllib

import pytest
import typer
import yaml

from common.config import FleetConfig, load_fleet
from deploy.testbed import DEFAULT_HOSTS

DEPLOY_DIR = Path(__file__).resolve().parents[2] / "deploy"
COMPOSE_FILE = DEPLOY_DIR / "docker-compose.yml"
SERVICES = ("registry", "robot", "edge-1", "edge-2", "cloud-1")
OBSERVERS = ("prometheus", "grafana")
"""Services beside the fleet: they scrape and draw its metrics (docs/metrics.md)."""
PROMETHEUS_FILE = DEPLOY_DIR / "prometheus.yml"
DASHBOARD_FILE = DEPLOY_DIR / "grafana" / "elasticfog.json"
METRICS_DOC = DEPLOY_DIR.parent / "docs" / "metrics.md"
# Commands a service's shell may run before it execs the daemon (the robot shapes its uplink).
SHELL_TOOLS = {"tc", "ip"}
# The daemon each `elasticfog` subcommand runs, and the role its --id must have in the fleet.
DAEMON_ROLE = {"cloud": "cloud", "robot": "robot"}


def _copied_sources(dockerfile: Path) -> list[str]:
    """The build-context paths the Dockerfile's COPY lines take (not those from another stage)."""
    sources: list[str] = []
    for line in dockerfile.read_text().splitlines():
        words = line.split()
        if words[:1] == ["COPY"] and not any(w.startswith("--from=") for w in words):
            sources += [w for w in words[1:-1] if not w.startswith("--")]
    return sources


def _compose() -> dict[str, Any]:
    data = yaml.safe_load(COMPOSE_FILE.read_text())
    assert isinstance(data, dict), f"{COMPOSE_FILE} is not a mapping"
    return data


def _service(name: str) -> dict[str, Any]:
    services = _compose()["services"]
    assert name in services, f"{COMPOSE_FILE} has no service {name!r}"
    return dict(services[name])


def _bind_mounts(service: dict[str, Any]) -> dict[str, Path]:
    """Container path → host path for the service's bind mounts (short syntax, ./relative)."""
    mounts: dict[str, Path] = {}
    for volume in service.get("volumes", []):
        source, target = str(volume).split(":")[:2]
        if source.startswith((".", "/")):
            mounts[target] = (DEPLOY_DIR / source).resolve()
    return mounts


def _elasticfog_argv(command: list[str]) -> list[str]:
    """The `elasticfog ...` argv of a service command: direct, or exec'd at the end of `sh -c`."""
    if command[:1] == ["elasticfog"]:
        return command
    assert command[:2] == ["/bin/sh", "-c"] and len(command) == 3, (
        f"a command is either [elasticfog, ...] or [/bin/sh, -c, SCRIPT], got {command}"
    )
    steps = [shlex.split(step) for step in command[2].split("&&")]
    *setup, last = steps
    for step in setup:
        assert step and step[0] in SHELL_TOOLS, f"unexpected setup step {step} in {command}"
    assert last[:2] == ["exec", "elasticfog"], (
        f"the script must end with `exec elasticfog ...`: {last}"
    )
    return last[1:]


def _root_command() -> Any:
    from common.cli import app  # assembled from every package's entry point

    return typer.main.get_command(app)


def _parse_cli(argv: list[str], mounts: dict[str, Path]) -> tuple[str, Any]:
    """Resolve `elasticfog SUB... OPTIONS` with the real CLI; returns the subcommand and the
    parsed context (nothing is invoked)."""
    assert argv[0] == "elasticfog"
    args = [str(mounts.get(a, a)) for a in argv[1:]]  # container paths → the mounted files
    command = _root_command()
    path: list[str] = []
    while isinstance(getattr(command, "commands", None), dict):  # a command group
        assert args, f"`{shlex.join(argv)}` stops at a command group"
        name = args.pop(0)
        sub = command.commands.get(name)
        assert sub is not None, (
            f"`{shlex.join(argv)}`: the CLI has no command `{' '.join([*path, name])}` "
            f"(it has: {', '.join(sorted(command.commands))})"
        )
        command, path = sub, [*path, name]
    try:
        ctx = command.make_context(" ".join(["elasticfog", *path]), args)
    except typer.TyperException as exc:
        message = exc.format_message() if hasattr(exc, "format_message") else str(exc)
        pytest.fail(f"`{shlex.join(argv)}` is not a valid command line: {message}")
    return " ".join(path), ctx


def _option_value(ctx: Any, option: str) -> Any:
    """The parsed value of `option` (whatever the parameter is called in the code)."""
    for param in ctx.command.params:
        if option in param.opts and param.name is not None:
            return ctx.params.get(param.name)
    pytest.fail(f"`{ctx.info_name}` has no option {option}")


def _fleet_for(service: dict[str, Any]) -> FleetConfig:
    mounts = _bind_mounts(service)
    configs = [p for t, p in mounts.items() if t.endswith((".yaml", ".yml"))]
    assert len(configs) == 1, f"expected one mounted fleet file, got {mounts}"
    return load_fleet(configs[0])


def test_compose_has_the_testbed_hosts() -> None:
    services = _compose()["services"]
    assert set(services) == set(SERVICES) | set(OBSERVERS)
    # The namespace testbed's default hosts are the same, so the fleet file runs in both.
    assert set(DEFAULT_HOSTS) == set(SERVICES)


@pytest.mark.parametrize("name", SERVICES)
def test_service_builds_from_files_that_exist(name: str) -> None:
    service = _service(name)
    build = service["build"]
    context = (DEPLOY_DIR / build["context"]).resolve()
    dockerfile = context / build["dockerfile"]
    assert context.is_dir(), f"{name}: build context {context} is missing"
    assert dockerfile.is_file(), f"{name}: Dockerfile {dockerfile} is missing"
    for source in _copied_sources(dockerfile):
        assert (context / source).exists(), f"Dockerfile copies missing {source}"
    for target, source in _bind_mounts(service).items():
        assert source.exists(), f"{name}: {source} (mounted at {target}) is missing"
    named = {str(v).split(":")[0] for v in service.get("volumes", [])} - {
        str(v).split(":")[0] for v in service.get("volumes", []) if str(v).startswith((".", "/"))
    }
    assert named <= set(_compose().get("volumes") or {}), f"{name}: undeclared volumes {named}"


def test_mounted_fleet_is_valid_and_off_shared_memory() -> None:
    fleet = _fleet_for(_service("registry"))
    assert fleet.zenoh.shared_memory is False, "shared memory bypasses the shaped links"
    for machine in fleet.machines.values():
        assert machine.shared_memory in (None, False)
    host = fleet.registry.endpoint.split("/", 1)[1].rsplit(":", 1)[0]
    assert host in SERVICES, f"registry endpoint {fleet.registry.endpoint} names no service"
    assert set(fleet.deployment_ids) == {"edge-1", "edge-2", "cloud-1"}


@pytest.mark.parametrize("name", SERVICES)
def test_command_is_a_real_elasticfog_command(name: str) -> None:
    service = _service(name)
    mounts = _bind_mounts(service)
    argv = _elasticfog_argv(list(service["command"]))
    subcommand, ctx = _parse_cli(argv, mounts)
    expected = {"registry": "registry", "robot": "robot"}.get(name, "cloud")
    assert subcommand == expected, f"{name} runs `elasticfog {subcommand}`"
    if subcommand in DAEMON_ROLE:
        machine_id = _option_value(ctx, "--id")
        assert machine_id, f"{name}: `elasticfog {subcommand}` without --id"
        _fleet_for(service).machine(str(machine_id), DAEMON_ROLE[subcommand])  # type: ignore[arg-type]


@pytest.mark.parametrize("name", SERVICES)
def test_healthcheck_uses_the_cli(name: str) -> None:
    service = _service(name)
    test = list(service["healthcheck"]["test"])
    assert test[0] == "CMD", f"{name}: healthcheck should be exec form [CMD, elasticfog, ...]"
    subcommand, ctx = _parse_cli(test[1:], _bind_mounts(service))
    assert subcommand in {"deployments", "robots", "routes"}
    assert _option_value(ctx, "--json") is True, f"{name}: healthcheck output is for scripts"
    for key in ("interval", "timeout", "retries"):
        assert key in service["healthcheck"], f"{name}: healthcheck without {key}"


def test_robot_shapes_its_uplink_with_net_admin() -> None:
    robot = _service("robot")
    assert "NET_ADMIN" in robot.get("cap_add", [])
    script = robot["command"][2]
    assert "tc qdisc replace dev eth0 root" in script and "htb" in script
    assert "ROBOT_UPLINK_MBIT" in robot.get("environment", {})
    for name in SERVICES:
        if name != "robot":
            assert "NET_ADMIN" not in _service(name).get("cap_add", [])


def test_clouds_and_robot_start_after_their_dependencies_are_healthy() -> None:
    for name in SERVICES:
        depends = _service(name).get("depends_on", {})
        for dependency, condition in depends.items():
            assert dependency in SERVICES
            assert condition == {"condition": "service_healthy"}
    assert "registry" in _service("edge-1")["depends_on"]
    assert set(_service("robot")["depends_on"]) == {"edge-1", "edge-2", "cloud-1"}


def test_prometheus_scrapes_every_daemon_on_its_metrics_port() -> None:
    """Each fleet service is a target at the port its machine serves /metrics on."""
    fleet = _fleet_for(_service("registry"))
    ports = {"registry": fleet.registry.metrics.port}
    ports.update({m: fleet.machines[m].metrics.port for m in fleet.deployment_ids})
    ports["robot"] = fleet.machines["robot-1"].metrics.port
    assert all(p is not None for p in ports.values()), ports
    config = yaml.safe_load(PROMETHEUS_FILE.read_text())
    targets = {
        t for job in config["scrape_configs"] for sc in job["static_configs"] for t in sc["targets"]
    }
    assert targets == {f"{host}:{port}" for host, port in ports.items()}
    mounts = _bind_mounts(_service("prometheus"))
    assert mounts["/etc/prometheus/prometheus.yml"] == PROMETHEUS_FILE.resolve()
    # Opt-in: their images come from a registry, the fleet must come up where none answers.
    for name in ("prometheus", "grafana"):
        assert _service(name)["profiles"] == ["metrics"], name
    assert "profiles" not in _service("registry") and "profiles" not in _service("robot")


def test_dashboard_queries_only_documented_metrics() -> None:
    """Every metric the dashboard draws is one docs/metrics.md documents (a renamed metric
    would leave a panel empty), and the panels the operators need are there."""
    import json

    dashboard = json.loads(DASHBOARD_FILE.read_text())
    exprs = [t["expr"] for p in dashboard["panels"] for t in p["targets"]]
    used = {
        re.sub(r"_(bucket|count|sum|total)$", "", n)
        for e in exprs
        for n in re.findall(r"elasticfog_[a-z_]+", e)
    }
    documented = {
        re.sub(r"_total$", "", n)
        for n in re.findall(r"^\| `(elasticfog_[a-z_]+)`", METRICS_DOC.read_text(), re.M)
    }
    assert used and used <= documented, used - documented
    titles = " / ".join(p["title"] for p in dashboard["panels"]).lower()
    for needed in ("frames/s", "p95", "actions", "fallbacks", "failovers", "per-deployment load"):
        assert needed in titles, f"no panel for {needed}"
    mounts = _bind_mounts(_service("grafana"))
    assert DASHBOARD_FILE.resolve() in mounts.values()


# --- The image's build context (deploy/Dockerfile.dockerignore) and what the Dockerfile installs.

REPO = DEPLOY_DIR.parent
DOCKERFILE = DEPLOY_DIR / "Dockerfile"
DOCKERIGNORE = DEPLOY_DIR / "Dockerfile.dockerignore"
RUNTIME_LOCK = "requirements/runtime.lock"


def _pattern_regex(pattern: str) -> re.Pattern[str]:
    """A .dockerignore pattern as a regex over slash-separated context paths (Docker's rules:
    `**` any number of folders, `*` and `?` within one name)."""
    out, i = "", 0
    while i < len(pattern):
        if pattern.startswith("**/", i):
            out, i = out + "(?:.*/)?", i + 3
        elif pattern.startswith("**", i):
            out, i = out + ".*", i + 2
        elif pattern[i] == "*":
            out, i = out + "[^/]*", i + 1
        elif pattern[i] == "?":
            out, i = out + "[^/]", i + 1
        else:
            out, i = out + re.escape(pattern[i]), i + 1
    return re.compile(out + "$")


def _dockerignore() -> list[tuple[bool, re.Pattern[str]]]:
    """(is an exception `!`, pattern) in file order."""
    rules = []
    for raw in DOCKERIGNORE.read_text().splitlines():
        line = raw.strip()
        if not line or line.startswith("#"):
            continue
        negate = line.startswith("!")
        cleaned = posixpath.normpath(line.lstrip("!").strip()).lstrip("/")
        rules.append((negate, _pattern_regex(cleaned)))
    return rules


def _admitted(path: str, rules: list[tuple[bool, re.Pattern[str]]]) -> bool:
    """Whether the build context holds `path`: the last pattern matching it or one of its
    folders decides, as Docker does."""
    parts = path.split("/")
    prefixes = ["/".join(parts[: n + 1]) for n in range(len(parts))]
    excluded = False
    for negate, regex in rules:
        if any(regex.match(p) for p in prefixes):
            excluded = not negate
    return not excluded


def _top_level_packages() -> list[str]:
    """The top-level packages pyproject ships (its setuptools `include` patterns)."""
    pyproject = tomllib.loads((REPO / "pyproject.toml").read_text())
    include = pyproject["tool"]["setuptools"]["packages"]["find"]["include"]
    return sorted({pattern.rstrip("*").rstrip(".") for pattern in include})


def _package_files(package: str) -> list[str]:
    return [
        p.relative_to(REPO).as_posix()
        for p in (REPO / package).rglob("*")
        if p.is_file() and "__pycache__" not in p.parts
    ]


@pytest.mark.parametrize("package", _top_level_packages())
def test_build_context_admits_every_package(package: str) -> None:
    assert (REPO / package / "__init__.py").is_file(), f"pyproject lists {package}, not a package"
    rules = _dockerignore()
    left_out = [f for f in _package_files(package) if not _admitted(f, rules)]
    assert not left_out, f"{DOCKERIGNORE.name} leaves {package} files out of the image: {left_out}"
    assert package in _copied_sources(DOCKERFILE), f"deploy/Dockerfile does not COPY {package}"


def test_build_context_admits_what_the_dockerfile_copies_and_no_more() -> None:
    rules = _dockerignore()
    for source in _copied_sources(DOCKERFILE):
        assert _admitted(source, rules), f"Dockerfile copies {source}; {DOCKERIGNORE.name} drops it"
    for outside in ("tests/unit/test_compose.py", ".git/HEAD", ".venv/bin/python", "docs/x.md"):
        assert not _admitted(outside, rules), f"{outside} would be sent to the builder"
    for cache in ("common/__pycache__/zoo.cpython-311.pyc", "elasticfog.egg-info/PKG-INFO"):
        assert not _admitted(cache, rules)


def test_dockerignore_rules_follow_docker() -> None:
    rules = [(False, _pattern_regex("**")), (True, _pattern_regex("nav"))]
    assert _admitted("nav/stereo.py", rules) and not _admitted("navx/a.py", rules)
    rules.append((False, _pattern_regex("**/__pycache__")))
    assert not _admitted("nav/__pycache__/a.pyc", rules)
    assert not _admitted("__pycache__/a.pyc", rules)


def test_image_installs_the_runtime_lock_hash_checked_and_fetches_nothing_else() -> None:
    text = DOCKERFILE.read_text()
    steps = " ".join(text.replace("\\\n", " ").split())
    assert f"COPY {RUNTIME_LOCK} " in steps
    assert "--require-hashes" in steps and "-r /tmp/runtime.lock" in steps
    assert re.search(r"pip install --no-deps( --no-compile)? \.", steps), "the lock alone decides"
    # The base image is a build argument; no other index, no downloads, no torch.
    assert re.search(r"^ARG BASE_IMAGE=python:3\.11-slim$", text, re.M)
    assert re.search(r"^FROM \$\{BASE_IMAGE\} AS runtime$", text, re.M)
    for fetch in ("--index-url", "--extra-index-url", "--find-links", "curl ", "wget ", "ADD "):
        assert fetch not in steps, f"deploy/Dockerfile fetches with {fetch.strip()}"
    runtime = text[text.index("AS runtime") :]
    assert "torch" not in runtime.replace('"import torch"', "").replace("torch in", "")
    assert "--mount=type=secret,id=ca" in steps, "a proxy's CA is a build secret"
    lock = (REPO / RUNTIME_LOCK).read_text()
    assert "torch" not in lock and "matplotlib" not in lock and "scikit-image" not in lock

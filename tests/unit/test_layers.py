"""The product packages' imports point down (DESIGN.md, Layout): every `import`, at the top of a
module or inside a function, walked with `ast`. Nothing from `common` into the daemons, `deploy`,
`experiments` or `nav`; no two top-level packages that import each other; no circle of modules.
Guards against a lazy import that "only runs when needed" turning a layer upside down again."""

from __future__ import annotations

import ast
from collections.abc import Iterator
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
PACKAGES = (
    "common",
    "registry",
    "cloudd",
    "robotd",
    "nav",
    "deploy",
    "experiments",
    "perception",
)
# What each package may import, besides itself (a layer sees only those below it).
MAY_IMPORT = {
    "common": set(),
    "registry": {"common"},
    "cloudd": {"common"},
    "robotd": {"common"},
    "nav": {"common", "robotd"},
    "deploy": {"common", "registry", "cloudd", "robotd", "nav"},
    "experiments": {"common", "registry", "cloudd", "robotd", "nav", "deploy"},
    # Handlers shipped with elasticfog: a fleet names them, nothing imports them.
    "perception": {"common"},
}


def module_name(path: Path) -> str:
    parts = path.relative_to(ROOT).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def imports(path: Path, name: str | None = None) -> Iterator[str]:
    """Every module `path` (module `name`) imports, absolute, wherever the statement is."""
    here = (name or module_name(path)).split(".")
    package = here if path.name == "__init__.py" else here[:-1]
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            yield from (alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                stem = package[: len(package) - node.level + 1]
                base = ".".join([*stem, base] if base else stem)
            yield base
            # `from pkg import module` imports a module too
            yield from (f"{base}.{alias.name}" for alias in node.names)


def product_modules() -> dict[str, Path]:
    return {
        module_name(p): p for package in PACKAGES for p in sorted((ROOT / package).rglob("*.py"))
    }


def module_graph() -> dict[str, set[str]]:
    modules = product_modules()
    return {
        name: {m for m in imports(path) if m in modules and m != name}
        for name, path in modules.items()
    }


def test_every_package_imports_only_the_layers_below_it() -> None:
    wrong = sorted(
        f"{name} imports {target}"
        for name, targets in module_graph().items()
        for target in targets
        if (top := name.split(".")[0]) != (below := target.split(".")[0])
        and below not in MAY_IMPORT[top]
    )
    assert not wrong, "\n".join(wrong)


def test_no_two_packages_import_each_other() -> None:
    edges = {
        (name.split(".")[0], target.split(".")[0])
        for name, targets in module_graph().items()
        for target in targets
    }
    both_ways = sorted((a, b) for a, b in edges if a < b and (b, a) in edges)
    assert not both_ways, both_ways


def test_no_circle_of_modules() -> None:
    graph = module_graph()
    # A package's __init__ is imported with each of its modules: not an edge of a circle.
    graph = {
        name: {t for t in targets if not name.startswith(t + ".")}
        for name, targets in graph.items()
    }
    circles: list[list[str]] = []
    state: dict[str, int] = {}  # 1: on the path, 2: done

    def visit(name: str, path: list[str]) -> None:
        state[name] = 1
        for target in sorted(graph[name]):
            if state.get(target) == 1:
                circles.append([*path[path.index(target) :], target])
            elif target not in state:
                visit(target, [*path, target])
        state[name] = 2

    for name in sorted(graph):
        if name not in state:
            visit(name, [name])
    assert not circles, "\n".join(" -> ".join(c) for c in circles)


def test_the_walk_sees_lazy_and_relative_imports(tmp_path: Path) -> None:
    """The walk itself: an import inside a function counts like one at the top, and a relative
    import is resolved against the module's package."""
    source = tmp_path / "m.py"
    source.write_text(
        "def f():\n    from robotd.policies import check_policy\n"
        "from .sinks import ResultSink\nfrom . import ros2\n"
    )
    found = set(imports(source, "robotd.results.m"))
    assert {"robotd.policies", "robotd.results.sinks", "robotd.results.ros2"} <= found, found

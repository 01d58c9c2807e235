"""No import circles in src/gps_denied_onboard, and layers that point one way: a layered module graph (read
with ast, nothing imported).

An edge is any import statement anywhere in a module (top level, in a function, under TYPE_CHECKING):
a circle hidden in a function is still a circle in the design. ``from pkg import name`` is an edge to
``pkg.name`` when that is a module, else to ``pkg``; the implicit import of a package's ``__init__`` by
its submodules is not an edge.
"""

from __future__ import annotations

import ast
from pathlib import Path

from conftest import REPO_ROOT

SRC = REPO_ROOT / "src"
PACKAGE = "gps_denied_onboard"
#: The layers, lowest first, by the first name under the package ("" is the package's own
#: ``__init__``): a module imports its own layer and those below, never one above. The shared base
#: (helpers, the frame type, names, config, clocks, geodesy) serves the components; the build-time
#: exporters (``models``) stand on the components' runtime; everything not named (the composition root,
#: the pipeline, replay, bench, the CLI) is the application on top.
LAYERS: tuple[frozenset[str], ...] = (
    frozenset({"", "helpers", "camera", "constants", "config", "clock", "geo", "logging_setup"}),
    frozenset({"components"}),
    frozenset({"models"}),
)


def _modules(root: Path, package: str) -> dict[str, tuple[Path, bool]]:
    """Dotted module name -> (file, is a package's ``__init__``) of every module under ``root/package``."""
    out: dict[str, tuple[Path, bool]] = {}
    for path in sorted((root / package).rglob("*.py")):
        parts = list(path.relative_to(root).with_suffix("").parts)
        is_package = parts[-1] == "__init__"
        if is_package:
            parts = parts[:-1]
        out[".".join(parts)] = (path, is_package)
    return out


def import_graph(root: Path, package: str) -> dict[str, set[str]]:
    """Module -> the modules of ``package`` it imports (see the module docstring)."""
    modules = _modules(root, package)
    graph: dict[str, set[str]] = {}
    for name, (path, is_package) in modules.items():
        deps: set[str] = set()
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"), filename=str(path))):
            if isinstance(node, ast.Import):
                deps.update(a.name for a in node.names if a.name in modules)
            elif isinstance(node, ast.ImportFrom):
                if node.level:
                    here = name.split(".") if is_package else name.split(".")[:-1]
                    here = here[: len(here) - (node.level - 1)]
                    target = ".".join(here + ([node.module] if node.module else []))
                else:
                    target = node.module or ""
                for alias in node.names:
                    sub = f"{target}.{alias.name}"
                    if sub in modules:
                        deps.add(sub)
                    elif target in modules:
                        deps.add(target)
        deps.discard(name)
        graph[name] = deps
    return graph


def import_circles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan, iterative), each sorted."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    circles: list[list[str]] = []
    counter = 0
    for start in sorted(graph):
        if start in index:
            continue
        work = [(start, iter(sorted(graph[start])))]
        index[start] = low[start] = counter
        counter += 1
        stack.append(start)
        on_stack.add(start)
        while work:
            node, children = work[-1]
            child = next(children, None)
            if child is not None:
                if child not in index:
                    index[child] = low[child] = counter
                    counter += 1
                    stack.append(child)
                    on_stack.add(child)
                    work.append((child, iter(sorted(graph.get(child, ())))))
                elif child in on_stack:
                    low[node] = min(low[node], index[child])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[node])
            if low[node] == index[node]:
                component = []
                while True:
                    member = stack.pop()
                    on_stack.discard(member)
                    component.append(member)
                    if member == node:
                        break
                if len(component) > 1:
                    circles.append(sorted(component))
    return circles


def layer_of(module: str, package: str) -> int:
    """The index in ``LAYERS`` of ``module`` (a dotted name under ``package``); the application's is last."""
    first = module.removeprefix(package).lstrip(".").split(".", 1)[0]
    return next((i for i, names in enumerate(LAYERS) if first in names), len(LAYERS))


def upward_imports(graph: dict[str, set[str]], package: str) -> list[tuple[str, str]]:
    """Every (module, imported module) where the import reaches a higher layer, sorted."""
    return sorted(
        (module, dep)
        for module, deps in graph.items()
        for dep in deps
        if layer_of(dep, package) > layer_of(module, package)
    )


def test_import_graph_has_no_circles() -> None:
    """No two modules of the package import each other, directly or through others."""
    graph = import_graph(SRC, PACKAGE)
    assert len(graph) > 50 and any(graph.values())  # the walk found the package and its imports
    circles = import_circles(graph)
    assert not circles, "import circles (modules that import each other): " + "; ".join(
        " <-> ".join(c) for c in circles
    )


def test_import_graph_finds_a_circle_through_a_function_level_import(tmp_path: Path) -> None:
    """The check sees a circle that one side hides in a function (as c3_matcher's base/tile_features did)."""
    pkg = tmp_path / "pkg"
    (pkg / "sub").mkdir(parents=True)
    (pkg / "__init__.py").write_text("")
    (pkg / "sub" / "__init__.py").write_text("from pkg.sub import a\n")
    (pkg / "sub" / "a.py").write_text("from pkg.sub.b import thing\n")
    (pkg / "sub" / "b.py").write_text("def thing():\n    from .c import other\n")
    (pkg / "sub" / "c.py").write_text("from pkg.sub import a\n")
    (pkg / "leaf.py").write_text("import pkg.sub.a\n")
    circles = import_circles(import_graph(tmp_path, "pkg"))
    assert circles == [["pkg.sub.a", "pkg.sub.b", "pkg.sub.c"]]


def test_import_graph_layers_point_one_way() -> None:
    """No module imports a layer above its own: helpers never read a component (C7's contract lives in
    ``helpers.inference_contract``), components never read ``models`` (the manifest and the weight pins
    live in ``helpers``), and neither reads the application."""
    graph = import_graph(SRC, PACKAGE)
    assert any(layer_of(m, PACKAGE) == 0 for m in graph) and any(layer_of(m, PACKAGE) == 2 for m in graph)
    upward = upward_imports(graph, PACKAGE)
    assert not upward, "imports that run up a layer: " + "; ".join(f"{a} -> {b}" for a, b in upward)


def test_import_graph_finds_an_upward_import(tmp_path: Path) -> None:
    """The check sees a helper that reads a component and a component that reads the exporters, even
    inside a function, and lets the application read every layer."""
    pkg = tmp_path / "pkg"
    for sub in ("helpers", "components", "models", "runtime_root"):
        (pkg / sub).mkdir(parents=True)
        (pkg / sub / "__init__.py").write_text("")
    (pkg / "__init__.py").write_text("")
    (pkg / "helpers" / "h.py").write_text("def f():\n    from pkg.components.c import thing\n")
    (pkg / "components" / "c.py").write_text("from pkg.models.m import x\nfrom pkg.helpers import h\n")
    (pkg / "models" / "m.py").write_text("from pkg.components import c\n")
    (pkg / "runtime_root" / "r.py").write_text("from pkg.models import m\nfrom pkg.helpers import h\n")
    assert upward_imports(import_graph(tmp_path, "pkg"), "pkg") == [
        ("pkg.components.c", "pkg.models.m"),
        ("pkg.helpers.h", "pkg.components.c"),
    ]

"""The import graph of ``src/knockgs_core``, module by module, is a DAG that never runs back up.

Every ``.py`` file under ``src/knockgs_core`` is parsed with :mod:`ast` (the sources, not the
installed package); every ``import`` and ``from ... import`` anywhere in it counts, at module
level, inside functions and methods (a deferred import is still a dependency: it only runs
later) and under ``if TYPE_CHECKING:`` (an annotation that names a type is a dependency of the
design, if not of the interpreter). Relative imports are resolved against the importing module.

Nodes are the package's modules; a package is its ``__init__``, named by the package
(``knockgs_core.sim`` is ``sim/__init__.py``). An import gives these edges:

* ``import knockgs_core.a.b``: an edge to ``knockgs_core.a.b``;
* ``from P import name``: an edge to the submodule ``P.name`` if that is a module (``from .
  import _kernels``), else to ``P`` itself (to a package's ``__init__`` for a package);
* importing ``P.x`` runs the ``__init__`` of every package on the way to it first, so the
  importer also gets an edge to each of those packages' ``__init__`` -- except to the
  packages it lies in itself: a module's own package has started initialising before the
  module's first line runs, so importing it again (implicitly) changes nothing.

The ``__init__`` rule. A package's ``__init__`` importing its own submodules is how a package
re-exports its names: those edges point down the tree and are never a cycle on their own, so
nothing is exempted for them. A submodule is never charged with an edge to its own package's
``__init__`` for living in it (the last bullet above). But a submodule that *names* its parent
package in an import (``from . import SomeName``, where ``SomeName`` is not a submodule, or
``from .. import x`` in a subpackage) does get the edge, and when that ``__init__`` imports the
submodule back, directly or through other modules, that is a cycle and is reported: the
submodule then reads a half-built package, and works only by the order of the ``__init__``'s
lines. It changes nothing, and is no cycle, where the ``__init__`` does not reach the submodule
(``rollout`` reading ``knockgs_core.__version__`` from the top-level ``__init__``, which imports
no submodule). Likewise a module outside a package that imports any part of it depends on the
package's whole ``__init__``, and through it on every submodule the ``__init__`` re-exports,
because that is what runs.

Layers (:data:`LAYERS`, lowest first) name what may import what: a module may import modules
of its own layer or lower, never of a higher one. The top-level modules and packages are
assigned whole; a package's submodules are in its layer.
"""

from __future__ import annotations

import ast
import subprocess
import sys
from functools import lru_cache
from pathlib import Path

import pytest

PACKAGE = "knockgs_core"
ROOT = Path(__file__).resolve().parents[1] / "src" / PACKAGE

#: The layers, lowest first: a module imports only its own layer or lower ones.
LAYERS: tuple[tuple[str, ...], ...] = (
    # foundations: errors, files and formats, the Warp set-up, the device lock, lazy package names
    ("knockgs_core", "errors", "io", "_warp", "_device_claim", "_lazy"),
    # the simulator
    ("sim",),
    # what builds and runs one simulation: assets, the object contract, rollouts
    ("assets", "contract", "rollout"),
    # what reads simulations: descriptors, metrics, rendering, observation, calibration, the FEM reference
    ("descriptors", "metrics", "render", "observe", "calibration", "fem"),
    # the studies and what reports on them
    ("experiments", "discrepancy", "reporting", "audits"),
    # the command line
    ("cli", "__main__"),
)

#: What only the upper layers may import (the studies, the discrepancy loop, the command line).
UPPER = ("experiments", "cli", "discrepancy")


def _module_names() -> dict[str, Path]:
    """Every module of the package: dotted name -> file (a package is its ``__init__``)."""
    names = {}
    for path in sorted(ROOT.rglob("*.py")):
        parts = path.relative_to(ROOT.parent).with_suffix("").parts
        if parts[-1] == "__init__":
            parts = parts[:-1]
        names[".".join(parts)] = path
    return names


MODULES = _module_names()


def _is_package(name: str) -> bool:
    return MODULES[name].name == "__init__.py"


def _ancestors(name: str) -> list[str]:
    """The packages ``name`` lies in, outermost first (not ``name`` itself)."""
    parts = name.split(".")
    return [".".join(parts[:i]) for i in range(1, len(parts))]


def _own_packages(name: str) -> set[str]:
    """The packages whose ``__init__`` has started before ``name``'s first line runs."""
    return set(_ancestors(name)) | ({name} if _is_package(name) else set())


def _module_of(dotted: str) -> str | None:
    """The longest prefix of ``dotted`` that is a module of the package (None: outside it)."""
    parts = dotted.split(".")
    for i in range(len(parts), 0, -1):
        prefix = ".".join(parts[:i])
        if prefix in MODULES:
            return prefix
    return None


def _imports(name: str) -> list[tuple[str, int]]:
    """The modules of the package that ``name`` imports, each with the line of the import."""
    tree = ast.parse(MODULES[name].read_text(encoding="utf-8"), filename=str(MODULES[name]))
    here = name if _is_package(name) else name.rpartition(".")[0]  # what "." means in ``name``
    found: list[tuple[str, int]] = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            targets = [_module_of(alias.name) for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base_parts = here.split(".")
                base_parts = base_parts[: len(base_parts) - (node.level - 1)]
                base = ".".join(base_parts + ([node.module] if node.module else []))
            else:
                base = node.module or ""
            if _module_of(base) is None:
                continue
            targets = []
            for alias in node.names:
                sub = f"{base}.{alias.name}"
                targets.append(sub if sub in MODULES else _module_of(base))
        else:
            continue
        for target in targets:
            if target is None or target == name:
                continue
            found.append((target, node.lineno))
            own = _own_packages(name)
            found += [(pkg, node.lineno) for pkg in _ancestors(target) if pkg not in own]
    return found


@lru_cache(maxsize=1)
def import_graph() -> dict[str, dict[str, int]]:
    """module -> {imported module: line of the first import that makes the edge} (read-only)."""
    graph: dict[str, dict[str, int]] = {}
    for name in MODULES:
        edges: dict[str, int] = {}
        for target, line in _imports(name):
            edges.setdefault(target, line)
        graph[name] = edges
    return graph


def strongly_connected(graph: dict[str, dict[str, int]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan): each is a set of
    modules that import one another round a cycle, sorted."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    components: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph[v]):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                components.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return sorted(components)


def shortest_cycle(graph: dict[str, dict[str, int]], component: list[str]) -> list[str]:
    """A shortest cycle through the first module of a strongly connected component, closed
    (its first module repeated at the end)."""
    start = component[0]
    parent: dict[str, str] = {}
    frontier = [start]
    while frontier:
        nxt = []
        for v in frontier:
            for w in sorted(graph[v]):
                if w not in component:
                    continue
                if w == start:
                    path = [v]
                    while path[-1] != start:
                        path.append(parent[path[-1]])
                    return path[::-1] + [start]
                if w not in parent:
                    parent[w] = v
                    nxt.append(w)
        frontier = nxt
    raise AssertionError(f"no cycle through {start}")  # pragma: no cover (a component has one)


def _short(name: str) -> str:
    return name.removeprefix(PACKAGE + ".")


def _describe(graph: dict[str, dict[str, int]], component: list[str]) -> str:
    """The modules of a cycle, a shortest cycle among them, and every import inside them."""
    cycle = shortest_cycle(graph, component)
    inside = [f"      {_short(a)} (line {graph[a][b]}) -> {_short(b)}"
              for a in component for b in sorted(graph[a]) if b in component]
    return (f"  modules: {', '.join(_short(m) for m in component)}\n"
            f"    cycle: {' -> '.join(_short(m) for m in cycle)}\n"
            "    imports among them:\n" + "\n".join(inside))


def layer_of(name: str) -> int:
    """The layer of a module: that of the top-level module or package it lies in."""
    top = name if name == PACKAGE else name.split(".")[1]
    for i, layer in enumerate(LAYERS):
        if top in layer:
            return i
    raise AssertionError(f"{name}: in no layer of LAYERS (add its top-level module or package to one)")


def test_parser_resolves_the_import_forms():
    """Spot checks of the parser on imports whose form it must resolve."""
    graph = import_graph()
    # ``from . import _kernels`` is the subpackage, ``from ... import _warp`` (in it) a top-level module
    assert "knockgs_core.sim._kernels" in graph["knockgs_core.sim._solver"]
    assert "knockgs_core._warp" in graph["knockgs_core.sim._kernels._module"]
    # ``from . import __version__`` in a top-level module is the package's __init__
    assert "knockgs_core" in graph["knockgs_core.rollout"]
    # a package's __init__ re-exports its submodules
    assert "knockgs_core.sim._config" in graph["knockgs_core.sim"]
    # importing a submodule from outside runs the package's __init__ first
    assert {"knockgs_core.io._long_format", "knockgs_core.io"} <= set(graph["knockgs_core.rollout"])
    # a function-local import counts
    assert "knockgs_core.rollout" in graph["knockgs_core.discrepancy._forward"]
    # a submodule is not charged with its own package's __init__ for living in it
    assert "knockgs_core.sim" not in graph["knockgs_core.sim._solver"]


def test_every_module_is_in_a_layer_and_every_layer_name_is_a_module():
    for name in MODULES:
        layer_of(name)
    tops = {name.split(".")[1] if name != PACKAGE else PACKAGE for name in MODULES}
    named = [top for layer in LAYERS for top in layer]
    assert len(named) == len(set(named)), "a name in two layers"
    assert set(named) == tops, f"not a top-level module of the package: {sorted(set(named) - tops)}"


def test_no_import_cycle():
    graph = import_graph()
    components = strongly_connected(graph)
    if components:
        pytest.fail("import cycles among the modules of knockgs_core:\n" + "\n".join(_describe(graph, c) for c in components),
                    pytrace=False)


def test_imports_never_run_up_the_layers():
    graph = import_graph()
    upward = []
    for name, edges in sorted(graph.items()):
        for target, line in sorted(edges.items()):
            if layer_of(target) > layer_of(name):
                upward.append(f"  {name} (line {line}, layer {layer_of(name)}) -> {target} (layer {layer_of(target)})")
    if upward:
        pytest.fail("imports that run up the layers (tests/test_import_graph.py: LAYERS):\n" + "\n".join(upward), pytrace=False)


@pytest.mark.parametrize("upper", UPPER)
def test_lower_layers_never_import_the_studies_or_the_command_line(upper):
    """The named rule on its own (implied by the layers; a clearer message where it breaks)."""
    graph = import_graph()
    top = layer_of(f"{PACKAGE}.{upper}")
    bad = [f"  {name} (line {edges[t]}) -> {t}" for name, edges in sorted(graph.items())
           for t in sorted(edges) if (t == f"{PACKAGE}.{upper}" or t.startswith(f"{PACKAGE}.{upper}."))
           and layer_of(name) < top]
    if bad:
        pytest.fail(f"lower layers importing knockgs_core.{upper}:\n" + "\n".join(bad), pytrace=False)


if __name__ == "__main__":  # print the graph: python tests/test_import_graph.py
    for module, targets in sorted(import_graph().items()):
        print(module, "->", ", ".join(sorted(targets)) or "(nothing)")


def test_reading_contracts_tables_and_frames_does_not_start_warp():
    # the workflow's light jobs (estimates, evaluations, tables) and every Snakemake start read
    # contracts and studies: the simulator's and renderer's Warp modules are imported where they
    # run (knockgs_core.sim and knockgs_core.render import them on first use)
    code = ("import sys\n"
            "import knockgs_core.contract, knockgs_core.experiments, knockgs_core.rollout, knockgs_core.observe\n"
            "from knockgs_core.contract import load_contract\n"
            "load_contract('pillow', 'ci')\n"
            "print(sorted(m for m in sys.modules if m == 'warp' or m.startswith('knockgs_core.sim._kernels')))\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT.parents[1])
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.strip() == "[]", out.stdout
    # and the lazy names resolve to the modules that define them
    from knockgs_core import render, sim

    assert sim.simulate is sim._simulate.simulate and sim.MPMSolver is sim._solver.MPMSolver
    assert render.render is render._pipeline.render
    with pytest.raises(AttributeError):
        sim.no_such_name  # noqa: B018


def test_the_workflow_reads_its_names_without_starting_warp():
    """Every ``knockgs_core`` name a workflow file imports at parse time loads without Warp (the
    studies' and the loop's packages import a name's module on first use); the simulator's effects
    still load Warp when asked for. A fresh interpreter, so nothing is imported before."""
    import re

    names = []
    for smk in sorted((Path(__file__).resolve().parents[1] / "workflow" / "rules").rglob("*.smk")):
        names += re.findall(r"^from (knockgs_core[\w.]*) import ([^\n]+)", smk.read_text(), flags=re.M)
    assert {"knockgs_core.discrepancy", "knockgs_core.experiments"} <= {mod for mod, _ in names}
    code = "\n".join(f"from {mod} import {items}" for mod, items in names)
    code += "\nimport sys\nassert 'warp' not in sys.modules, sorted(m for m in sys.modules if m.startswith('knockgs_core.'))"
    code += "\nfrom knockgs_core.sim import with_effects\nassert 'warp' in sys.modules"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert out.returncode == 0, out.stderr[-2000:]

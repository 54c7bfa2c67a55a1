"""The package's layout: modules import along the data flow, never in a cycle, and stay short.

The import graph is read from the sources with :mod:`ast` (module-level imports and those
inside functions alike, so a cycle cannot hide behind a deferred import).
"""

from __future__ import annotations

import ast
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1] / "bayesreg"

# The data flow, lowest layer first: a module may import modules of its own layer or of
# lower ones, never of a higher one.  Names are relative to ``bayesreg``; a package's
# ``__init__`` is the package's name ("bayesreg" for the top-level one).
LAYERS = [
    ["_checks", "_files", "jaxconfig", "stages", "config.models", "config.loading",
     "config.calibration", "config", "_tetwild_worker"],
    ["images"],
    ["interpolation"],
    ["constraints"],  # the skull: one smooth signed distance (meshing checks the rest state)
    ["labels"],
    ["datasets"],
    ["mesh"],
    ["warp"],
    ["transforms"],  # displacement fields as ITK/ANTs files, the FE map on points
    ["meshing"],
    ["fem"],
    ["stiffness"],
    ["preconditioners"],
    ["solver"],
    ["similarity"],
    ["parameters"],
    ["normaliser"],
    ["posterior"],
    ["registration"],
    ["synthetic"],
    ["contact"],
    ["kernels.base", "kernels"],
    ["kernels.rwmh"],
    ["kernels.target"],
    ["kernels.gibbs"],
    ["kernels.adaptation"],
    ["convergence"],
    ["chains"],
    ["sampler"],
    ["problem"],
    ["targets"],
    ["mode"],
    ["initialisation"],
    ["diagnostics"],
    ["fields"],
    ["rundir"],
    ["checkpoint"],
    ["plots"],
    ["outputs"],
    ["apply"],
    ["pipeline"],
    ["calibration"],  # simulation-based calibration: a small problem, many replicas
    ["report.data"],
    ["report.tables", "report.figures"],
    ["report.write"],
    ["report"],
    ["sweep"],  # many runs on Dask distributed
    ["bayesreg"],  # the public API: configure_jax, Config, run, prepare, ...
    ["cli"],  # the command line, on top of the public API
]

# Modules allowed beyond MAX_LINES, with the reason.
MAX_LINES = 650
LONG_MODULES = {
    "config.models": "every key's description is its documentation (the configuration reference "
                     "is generated from it)",
    "sampler": "the driver's two entry points carry their full parameter documentation",
    "posterior": "the Posterior type and its entry points carry their full field and parameter "
                 "documentation, with examples (about half the module is docstrings)",
}


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(PACKAGE).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts) or "bayesreg"


MODULES = {_module_name(p): p for p in sorted(PACKAGE.rglob("*.py"))}


def _resolve(name: str) -> str | None:
    """The module of ``bayesreg.<name>`` (a name inside a module: that module)."""
    while name:
        if name in MODULES:
            return name
        name = name.rpartition(".")[0]
    return None


def _imports(module: str) -> set[str]:
    """Every bayesreg module that ``module`` imports, at module level or inside a function."""
    path = MODULES[module]
    package = module if path.name == "__init__.py" else module.rpartition(".")[0]
    out = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            targets = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:  # relative: from the module's package upward
                base = package.split(".") if package and package != "bayesreg" else []
                base = base[: len(base) - (node.level - 1)] if node.level > 1 else base
                stem = ".".join(base + ([node.module] if node.module else []))
                stem = "bayesreg." + stem if stem else "bayesreg"
            else:
                stem = node.module
            # ``from bayesreg.kernels import gibbs`` imports the submodule kernels.gibbs
            targets = [f"{stem}.{a.name}" for a in node.names] + [stem]
            sub = [t for t in targets[:-1] if t.startswith("bayesreg.") and _resolve(t[9:]) == t[9:]]
            targets = sub or [stem]
        else:
            continue
        for t in targets:
            if t == "bayesreg":
                out.add("bayesreg")
            elif t.startswith("bayesreg."):
                resolved = _resolve(t[len("bayesreg."):])
                if resolved is not None:
                    out.add(resolved)
    out.discard(module)
    return out


GRAPH = {m: _imports(m) for m in MODULES}


def test_every_module_has_a_layer():
    placed = [m for layer in LAYERS for m in layer]
    assert len(placed) == len(set(placed)), "a module is in two layers"
    assert set(placed) == set(MODULES), (sorted(set(MODULES) - set(placed)), sorted(set(placed) - set(MODULES)))


def _find_cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """A cycle of ``graph`` as its path ``[a, b, ..., a]`` (depth-first search: a back edge
    closes one), or ``None``."""
    state: dict[str, int] = {}  # 1 on the stack, 2 done
    stack: list[str] = []

    def visit(m):
        state[m] = 1
        stack.append(m)
        for n in sorted(graph.get(m, ())):
            if state.get(n) == 1:
                return stack[stack.index(n):] + [n]
            if n not in state:
                found = visit(n)
                if found:
                    return found
        stack.pop()
        state[m] = 2
        return None

    for m in sorted(graph):
        if m not in state:
            found = visit(m)
            if found:
                return found
    return None


def test_the_import_graph_has_no_cycle():
    assert _find_cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == ["a", "b", "c", "a"]
    assert _find_cycle({"a": {"b"}, "b": set(), "c": {"a", "b"}}) is None
    cycle = _find_cycle(GRAPH)
    assert cycle is None, "import cycle: " + " -> ".join(cycle)


def _upward(graph: dict[str, set[str]], layers: list[list[str]]) -> list[str]:
    """The edges ``"m -> n"`` of ``graph`` from a module to one of a higher layer."""
    level = {m: k for k, layer in enumerate(layers) for m in layer}
    return sorted(f"{m} -> {n}" for m, deps in graph.items() for n in deps if level[n] > level[m])


def test_no_module_imports_a_higher_layer():
    """Every import runs down the data flow (or within a layer)."""
    assert _upward({"a": {"b"}, "b": set(), "c": {"a"}}, [["a"], ["b", "c"]]) == ["a -> b"]
    upward = _upward(GRAPH, LAYERS)
    assert not upward, "imports against the data flow: " + ", ".join(upward)


def test_the_graph_is_read_from_both_kinds_of_import():
    """The reader sees module-level and function-level imports, absolute and relative, and
    a submodule imported by ``from package import module``."""
    assert {"chains", "kernels.gibbs", "kernels.rwmh", "kernels.adaptation"} <= GRAPH["sampler"]
    assert {"config.loading", "config.models"} <= GRAPH["config"]
    assert "report.data" in GRAPH["report.tables"]
    # the brain fixture's modules: meshing imports mesh and warp
    assert {"mesh", "warp"} <= GRAPH["meshing"]


def test_no_private_name_is_imported_across_modules():
    """Modules share public names only (the internal ``_checks`` and ``_files`` modules
    included: their names are public); a leading underscore stays inside its module."""
    private = []
    for module, path in MODULES.items():
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.ImportFrom) and (node.level or (node.module or "").startswith("bayesreg")):
                private += [f"{module}: {a.name} from {node.module}" for a in node.names
                            if a.name.startswith("_") and not a.name.startswith("__")]
    assert not private, private


def test_modules_stay_short():
    """No module over MAX_LINES lines unless listed, with its reason, in LONG_MODULES; a
    listed module that has become short leaves the list."""
    lengths = {m: len(p.read_text().splitlines()) for m, p in MODULES.items()}
    long = {m: n for m, n in lengths.items() if n > MAX_LINES}
    assert set(long) <= set(LONG_MODULES), {m: n for m, n in long.items() if m not in LONG_MODULES}
    assert set(LONG_MODULES) <= set(long), f"no longer over {MAX_LINES} lines: {set(LONG_MODULES) - set(long)}"

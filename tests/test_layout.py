"""The package's layout: modules import along the data flow, never in a cycle, and stay short.

The import graph is read from the sources with :mod:`ast` (module-level imports and those
inside functions alike, so a cycle cannot hide behind a deferred import).
"""

from __future__ import annotations

import ast
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1] / "bayesreg"

# The rooms of the package, in the order of the data flow: a subpackage, or a top-level module
# of the run shell.  A module may import modules of its own room or of earlier rooms, never of a
# later one, so the file tree reads as the method: data -> mesh -> FE -> model -> sampling ->
# outputs, with the run shell (config, run directory, checkpoint, pipeline, CLI) around it.
ROOMS = [
    "_checks", "_files", "jaxconfig", "stages", "config", "rundir",  # the shell's base
    "data",         # images, labels, data sources, an optical-flow registration
    "mesh",         # the mesh, its FE map on grids, the constraints on its motion, meshing
    "interop",      # displacement fields as ITK/ANTs/Slicer files; the FE map at points
    "fem",          # elements, K, the interior solve, preconditioners, the normaliser
    "truth",        # synthetic truths and the paper's constrained truth
    "model",        # similarity, elastic parameters, the posterior, a problem from a config
    "sampling",     # kernels, chain scheduler, driver, convergence, diagnostics
    "inference",    # a problem and a config to the sampler's targets, mode and starts
    "outputs",      # a finished run's field statistics, figures, tables, verdict
    "report",       # the paper's Tables and Figures from run directories
    "checkpoint", "pipeline", "apply",  # the run shell: the main job, a finished run's posterior
    "experiments",  # calibration and sweeps built on the main job
    "bayesreg",     # the public API: configure_jax, Config, run, prepare, ...
    "cli",          # the command line, on top of the public API
]

# The data flow within the rooms, lowest layer first: a module may import modules of its own
# layer or of lower ones, never of a higher one.  Names are relative to ``bayesreg``; a
# package's ``__init__`` is the package's name ("bayesreg" for the top-level one).
LAYERS = [
    ["_checks", "_files", "jaxconfig", "stages", "config.models", "config.loading",
     "config.calibration", "config", "rundir"],
    ["data", "data.images"],
    ["data.interpolation"],
    ["data.labels"],
    ["data.datasets"],
    ["data.registration"],
    ["mesh", "mesh._tetwild_worker", "mesh.constraints"],  # the skull: one smooth signed distance
    ["mesh.tetmesh"],
    ["mesh.warp"],
    ["mesh.meshing"],
    ["interop", "interop.transforms"],
    ["interop.syn"],
    ["fem", "fem.element"],
    ["fem.stiffness"],
    ["fem.preconditioners"],
    ["fem.solver"],
    ["fem.normaliser"],
    ["truth", "truth.synthetic"],
    ["truth.contact"],
    ["model", "model.similarity"],
    ["model.lncc"],
    ["model.parameters"],
    ["model.posterior"],
    ["model.problem"],
    ["sampling", "sampling.kernels.base", "sampling.kernels"],
    ["sampling.chains"],
    ["sampling.kernels.rwmh"],
    ["sampling.kernels.target"],
    ["sampling.kernels.adaptation", "sampling.kernels.collapsed", "sampling.kernels.surrogate"],
    ["sampling.kernels.gibbs"],
    ["sampling.convergence"],
    ["sampling.driver"],
    ["sampling.diagnostics"],
    ["inference", "inference.targets"],
    ["inference.mode"],
    ["inference.initialisation"],
    ["outputs", "outputs.fields"],
    ["outputs.plots", "outputs.printed"],
    ["outputs.result"],
    ["outputs.write"],
    ["report.data"],
    ["report.tables", "report.figures"],
    ["report.write"],
    ["report"],
    ["checkpoint"],
    ["pipeline"],
    ["apply"],
    ["experiments", "experiments.calibration"],  # simulation-based calibration
    ["experiments.sweep"],  # many runs on Dask distributed
    ["bayesreg"],  # the public API: configure_jax, Config, run, prepare, ...
    ["cli"],  # the command line, on top of the public API
]

# Modules allowed beyond MAX_LINES, with the reason.
MAX_LINES = 650
LONG_MODULES = {
    "config.models": "every key's description is its documentation (the configuration reference "
                     "is generated from it)",
    "model.posterior": "the Posterior type and its entry points carry their full field and parameter "
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
            # ``from bayesreg.sampling.kernels import gibbs`` imports the submodule sampling.kernels.gibbs
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
    assert {"sampling.chains", "sampling.kernels.adaptation", "sampling.kernels.target"
            } <= GRAPH["sampling.kernels.gibbs"]
    assert {"sampling.kernels.gibbs", "sampling.kernels.rwmh"} <= GRAPH["inference.targets"]
    assert {"config.loading", "config.models"} <= GRAPH["config"]
    assert "report.data" in GRAPH["report.tables"]
    # the brain fixture's modules: meshing imports mesh and warp
    assert {"mesh.tetmesh", "mesh.warp"} <= GRAPH["mesh.meshing"]


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


def room(module: str) -> str:
    """The room of a module: its subpackage, or the top-level module itself."""
    return module.split(".")[0]


def test_every_module_lives_in_a_room():
    assert len(ROOMS) == len(set(ROOMS))
    assert {room(m) for m in MODULES} == set(ROOMS), {room(m) for m in MODULES} ^ set(ROOMS)


def test_no_room_imports_a_later_room():
    """The rooms follow the data flow: a module imports its own room or earlier ones."""
    order = {r: k for k, r in enumerate(ROOMS)}
    later = sorted(f"{m} -> {n}" for m, deps in GRAPH.items() for n in deps
                   if order[room(n)] > order[room(m)])
    assert not later, "imports of a later room: " + ", ".join(later)


def test_the_layers_keep_the_rooms_together():
    """LAYERS lists each room's modules in one run, in the order of ROOMS (so the layers are
    the rooms' data flow, refined)."""
    rooms = [room(m) for layer in LAYERS for m in layer]
    runs = [r for k, r in enumerate(rooms) if k == 0 or r != rooms[k - 1]]
    base = set(ROOMS[:6])
    runs = ["base" if r in base else r for r in runs]
    runs = [r for k, r in enumerate(runs) if k == 0 or r != runs[k - 1]]
    assert runs == ["base"] + ROOMS[6:], runs

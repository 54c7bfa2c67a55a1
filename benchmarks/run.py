"""Speed benchmark of bayesreg's posterior and Metropolis-Hastings sampler.

Run from the repository root (not part of the test suite)::

    python benchmarks/run.py                         # meshes 16, 10, 7 mm; 1, 3, 16, 64 chains
    python benchmarks/run.py --quick --chains 1,3    # smoke test: one coarse mesh, short timings
    python benchmarks/run.py --chains 64,256,1024    # on a GPU (JAX picks the device)
    python benchmarks/run.py --quickstart            # also time the quickstart job to R-hat

Problems are the paper's three-compartment configuration (``configs/paper_three_compartment.yaml``)
with the mesh edge length of ``--meshes`` (``EDGE`` or ``EDGE@RESOLUTION``, mm; 16, 10 and 7 mm
give about 900, 3300 and 9800 nodes) and, by default, a smooth synthetic truth of 7.5 mm (the
paper's constrained truth does not scale to 10k nodes; the cost of a step does not depend on
it); they are built once and cached in ``benchmarks/.cache/`` (meshing is not
bit-reproducible: the cached mesh is the one measured, its node count is reported).

Figures, per mesh (see ``benchmarks/README.md`` for how to read them):

1. **Log-density evaluations per second** of ``jit(vmap(logdensity))`` over ``C`` positions
   (the chains' starts), *cold* (interior CG solve started from zeros) and *warm* (started
   from the interior solution of a position one paper-kernel proposal away); with the CG
   iterations per solve (mean and max over the ``C`` positions).  Under ``vmap`` a
   ``while_loop`` runs until its slowest member has converged.
2. **The pieces of a step timed alone**, each jitted and run 20 times inside one
   ``lax.scan`` (as in the sampler: no dispatch per call) on slightly jittered inputs, timed
   after warm-up calls with ``block_until_ready``: the interior solve
   (:func:`bayesreg.solver.solve_interior_blocks`, cold and warm, including the assembly of
   ``K``'s blocks by :func:`bayesreg.posterior.stiffness_blocks`), the similarity
   (:func:`bayesreg.similarity.ssd` of a full displacement), the whole log-density (warm),
   and the proposal (a Normal draw times the jumping-kernel scale: the paper's vector
   ``sigma``, the blocked kernel's dense Laplace factor).  The solves use the paper-joint
   sampler's CG preconditioner (its dense ``K_ii^-1``, whose build, once per chunk, is timed
   too; else spectral or block Jacobi), so they are the pieces of its step.  Alone, a piece
   has the caches to itself: in the running chains the same pieces cost several times more
   (figure 2b), so they do not add up to a step.

   2b. **Time split inside the sampler**: after each row's timed chunks of figure 3, one more
   chunk runs under :func:`jax.profiler` (Python tracing off), and every XLA operation's
   exclusive time is filed under the part of the step it was compiled from (the
   :func:`jax.named_scope` names of the log-density and the kernel: stiffness combination,
   solve, similarity, strain energy, constraints, proposal, accept, the chunk-start cache
   build; then control flow and the rest), read from the HLO that XLA dumps
   (``benchmarks/profiling.py``).  Milliseconds per MH step summed over threads, their
   shares, the profiled chunk's wall time per step beside the timed chunks' (the
   profiler's own cost), and "busy", seconds of operations per second profiled (on a CPU
   the mean number of busy threads; on a GPU, where the device's own kernels and copies
   are read, the share of the time the device works).  At most
   ``--split-profile-seconds`` of the chunk are profiled (the profiler keeps every event
   in memory): a longer chunk in a window that opens a third of the way in (past the
   chains' chunk-start builds of their ``K_ii^-1``), its steps taken from the chunk's
   rate; on an accelerator the whole chunk, since a trace stopped while the device runs
   can break its context (``profiling.ChunkProfiler``).  ``--no-split-profile`` skips
   it; ``--keep-profiles DIR`` keeps the traces and the step's compiled HLO.
3. **MH steps per second**, per chain and in total, for each chain count and two kernels:
   ``paper-joint`` (the paper's joint isotropic proposal, Eq. 14: ``sampler.blocked=false,
   proposal=isotropic``) and ``blocked-laplace`` (the blocked random walk: ``u_b`` with the
   Gauss-Newton Laplace factor, then the elastic parameters, two log-densities per step).
   :func:`bayesreg.sampler.sample` runs with no warm-up, a fixed number of draws (``min_draws
   = max_draws``), thinning 10, and ``chunk_draws`` sized so that a chunk lasts about
   ``--chunk-seconds`` (from figure 1's rate, or the total steps/s of the kernel's previous
   chain count where that is higher), but never so short that the chains' chunk-start build
   of their dense ``K_ii^-1`` exceeds about a tenth of a chunk; the
   first chunk (which compiles) is excluded by timing the chunks after it (``on_chunk``
   time stamps).  A step is one transition of every block.
   ``sample`` needs two chains or more (R-hat): one chain runs the same kernel
   (:func:`bayesreg.sampler.build_kernel`) in a jitted ``scan`` here (``--compare-vmap``: the
   same for every chain count, the chains vmapped on one device).
   Also reported: acceptance and CG iterations per solve over the timed chunks, and the
   ratio to the paper's 5 steps/s per chain.
4. **NumPy/SciPy reference** (``benchmarks/reference.py``): the same log posterior with a
   sparse direct solve (SuperLU, refactored whenever lam/mu change) and NumPy quadrature; its
   log-density is compared with JAX's at a few positions (maximum relative difference at the
   config's CG tolerance and at 1e-13), then a single chain runs the paper's joint kernel for
   ``--reference-seconds``: steps/s and JAX (1 chain, same kernel) / reference.
5. **Peak memory**: the process's maximum resident set size after each phase, and the device's
   peak bytes in use where JAX reports it (GPU).  Figure 2b's profiles are left out: the
   peak before each is kept and the kernel's peak counter (``VmHWM``) reset after it
   (:func:`peak_rss_mib`; where Linux does not allow that, the process's ``ru_maxrss``).

``--quickstart`` runs ``configs/quickstart.yaml`` end to end and reports its wall time, draws,
whether it converged, the bulk ESS of the slowest estimand per sampling second and when the
classic R-hat of every estimand first fell below 1.2.

Outputs: ``<out>/<UTC time>-<backend>-<host>.json`` and ``.md`` (also printed), with the
machine described (CPU model, cores, memory, JAX backend, version and devices, XLA_FLAGS,
git commit).
"""

from __future__ import annotations

import argparse
import datetime as _dt
import hashlib
import json
import math
import os
import platform
import resource
import socket
import subprocess
import sys
import tempfile
import time
import traceback
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import profiling  # noqa: E402  (benchmarks/profiling.py)

# figure 2b reads the compiled programs' HLO: XLA dumps it from its first backend on
HLO_DUMP = profiling.enable_hlo_dump()

from bayesreg import _xla  # noqa: E402

_xla.configure()  # XLA flags must be set before JAX starts
import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

from bayesreg import pipeline  # noqa: E402
from bayesreg.config import load_config  # noqa: E402
from bayesreg.posterior import (  # noqa: E402
    _precond_at,  # the solve's preconditioner, chosen as log_density chooses it
    elastic_groups,
    full_displacement,
    log_density,
    split_position,
    stiffness_blocks,
)
from bayesreg.sampler import sample  # noqa: E402
from bayesreg.similarity import ssd  # noqa: E402
from bayesreg.solver import solve_interior_blocks  # noqa: E402

from reference import ReferencePosterior, reference_mh  # noqa: E402
from samplers import cache_tag  # noqa: E402

REPO = Path(__file__).resolve().parent.parent
PAPER_CONFIG = REPO / "configs" / "paper_three_compartment.yaml"
QUICKSTART_CONFIG = REPO / "configs" / "quickstart.yaml"
PAPER_STEPS_PER_S = 5.0  # per chain (paper Sec. 4)
THINNING = 10
#: a chunk lasts at least this many times one chain's chunk-start build of its dense
#: ``K_ii^-1``: the sampler rebuilds it per chunk (1,000 steps in the configs, where the
#: build is 3% of a chunk at the paper's size); shorter chunks time the builds, not the steps
AMORTISE_BUILD = 10

KERNELS = {
    "paper-joint": ["sampler.blocked=false", "sampler.proposal=isotropic"],
    "blocked-laplace": ["sampler.blocked=true", "sampler.proposal=laplace"],
    # opt-in (--kernels): u_b moves from a cached dense condensation u_i = H(lam, mu) u_b
    "blocked-laplace-condensed": ["sampler.blocked=true", "sampler.proposal=laplace",
                                  "sampler.condensed=true"],
}
DEFAULT_KERNELS = ("paper-joint", "blocked-laplace")

#: settings of a full run and of ``--quick``
PROFILES = {
    "full": {"meshes": "16,10,7", "chunk_seconds": 2.0, "timed_chunks": 3, "time_target_s": 2.0,
             "reference_seconds": 10.0},
    "quick": {"meshes": "26@3", "chunk_seconds": 0.5, "timed_chunks": 2, "time_target_s": 0.5,
              "reference_seconds": 3.0},
}


# ---------------------------------------------------------------------------------------------
# helpers
# ---------------------------------------------------------------------------------------------

def log(msg: str) -> None:
    print(f"[{time.strftime('%H:%M:%S')}] {msg}", flush=True)


#: peak RSS (MiB) before the last reset of the kernel's peak counter (see :func:`peak_rss_mib`)
_PEAK_BEFORE_RESET = 0.0
_PEAK_RESETTABLE = None  # whether /proc/self/clear_refs resets VmHWM here (None: not tried)


def _vm_hwm_mib() -> float | None:
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    return None


def peak_rss_mib() -> float:
    """Maximum resident set size of this process so far (MiB), without the memory of figure
    2b's profiles where Linux lets the peak be reset (:func:`profile_memory_begin`,
    :func:`profile_memory_end`); else the whole process's (``ru_maxrss``, KiB on Linux)."""
    hwm = _vm_hwm_mib() if _PEAK_RESETTABLE else None
    if hwm is None:
        return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    return max(_PEAK_BEFORE_RESET, hwm)


def profile_memory_begin() -> None:
    """Before a profile: keep the peak so far (the profiler holds its events in memory)."""
    global _PEAK_BEFORE_RESET
    _PEAK_BEFORE_RESET = max(_PEAK_BEFORE_RESET, peak_rss_mib())


def profile_memory_end() -> None:
    """After a profile is read and freed: hand the freed memory back to the system and
    reset the kernel's peak counter (``/proc/self/clear_refs``), so that later phases'
    peaks do not hold the profile's.  Where that fails, peaks stay the process's."""
    global _PEAK_RESETTABLE
    if _PEAK_RESETTABLE is False:
        return
    try:
        import ctypes

        ctypes.CDLL("libc.so.6").malloc_trim(0)
    except (OSError, AttributeError):
        pass
    try:
        Path("/proc/self/clear_refs").write_text("5")
        _PEAK_RESETTABLE = _vm_hwm_mib() is not None
    except OSError:
        _PEAK_RESETTABLE = False


def device_memory() -> dict | None:
    """Peak/in-use bytes of the first JAX device where it reports them (GPU), else None."""
    try:
        stats = jax.devices()[0].memory_stats()
    except Exception:  # noqa: BLE001 - backends without memory stats
        return None
    if not stats:
        return None
    keys = ("peak_bytes_in_use", "bytes_in_use", "bytes_limit")
    return {k: int(stats[k]) for k in keys if k in stats}


def memory_snapshot(phase: str) -> dict:
    return {"phase": phase, "peak_rss_mib": round(peak_rss_mib(), 1), "device": device_memory()}


def block(x):
    return jax.block_until_ready(x)


def time_call(fn, *args, target_s: float, min_reps: int = 3, warmup: int = 2) -> dict:
    """Seconds per call of a jitted ``fn`` after ``warmup`` calls (the first compiles).

    Calls are repeated until ``target_s`` has passed and at least ``min_reps`` were made;
    returns the mean and the fastest call.
    """
    t = time.perf_counter()
    for _ in range(warmup):
        block(fn(*args))
    first = time.perf_counter() - t
    times = []
    t_start = time.perf_counter()
    while len(times) < min_reps or time.perf_counter() - t_start < target_s:
        t = time.perf_counter()
        block(fn(*args))
        times.append(time.perf_counter() - t)
    return {"mean_s": float(np.mean(times)), "min_s": float(np.min(times)), "reps": len(times),
            "warmup_incl_compile_s": first}


def machine_info() -> dict:
    """CPU, cores, memory, JAX backend/devices, XLA flags, git commit."""
    cpu = platform.processor() or "unknown"
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    mem_gib = None
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemTotal"):
                mem_gib = round(int(line.split()[1]) / 2**20, 1)
    except OSError:
        pass

    def git(*a):
        try:
            return subprocess.run(["git", *a], cwd=REPO, capture_output=True, text=True,
                                  timeout=10).stdout.strip()
        except (OSError, subprocess.SubprocessError):
            return None

    import jaxlib

    devices = jax.devices()
    return {
        "host": socket.gethostname(),
        "cpu_model": cpu,
        "cores_available": len(os.sched_getaffinity(0)),
        "cores_total": os.cpu_count(),
        "memory_gib": mem_gib,
        "load_average_at_start": [round(x, 2) for x in os.getloadavg()],
        "python": platform.python_version(),
        "jax": jax.__version__,
        "jaxlib": jaxlib.__version__,
        "backend": jax.default_backend(),
        "devices": [f"{d.platform}:{d.device_kind}" for d in devices],
        "device_count": len(devices),
        "xla_flags": os.environ.get("XLA_FLAGS", ""),
        "x64": bool(jax.config.read("jax_enable_x64")),
        "git_commit": git("rev-parse", "HEAD"),
        "git_dirty": bool(git("status", "--porcelain", "--untracked-files=no")),
    }


def atomic_write(path: Path, text: str) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    with os.fdopen(fd, "w") as fh:
        fh.write(text)
    os.replace(tmp, path)


def _jsonable(x):
    if isinstance(x, dict):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    if isinstance(x, (np.floating, float)):
        return None if not math.isfinite(float(x)) else float(x)
    if isinstance(x, (np.integer,)):
        return int(x)
    if isinstance(x, np.bool_):
        return bool(x)
    if isinstance(x, np.ndarray):
        return _jsonable(x.tolist())
    return x


# ---------------------------------------------------------------------------------------------
# problems
# ---------------------------------------------------------------------------------------------

def parse_mesh(spec: str) -> tuple[float, float]:
    """``"EDGE"`` or ``"EDGE@RESOLUTION"`` (mm) -> ``(edge, resolution)``; resolution 2 mm by default."""
    edge, _, res = spec.partition("@")
    return float(edge), float(res) if res else 2.0


def mesh_overrides(edge: float, res: float, args) -> list[str]:
    """Config overrides of one benchmark problem (mesh, image resolution, synthetic truth)."""
    # one mesh at the edge length (the paper config's mesh.target_nodes would re-mesh to 801 nodes)
    out = [f"mesh.edge_length_mm={edge:g}", "mesh.target_nodes=null", f"data.resolution_mm={res:g}",
           f"synthetic.truth={args.truth}"]
    if args.shift_mm is not None:
        out.append(f"synthetic.shift_mm={args.shift_mm:g}")
    return out


def build_problem(edge: float, res: float, args) -> tuple:
    """The paper problem with this mesh, from ``benchmarks/.cache/`` or built (and cached).

    A synthetic truth that inverts an element or moves a node into the skull (the smooth
    truth on fine meshes can) is retried on a new mesh with half the shift, twice at most;
    the shift used is in ``info["truth_info"]``.  The truth does not change the cost of a step.

    Returns ``(problem, cfg, info)``; ``info`` holds the mesh size and how long it took.
    """
    overrides = mesh_overrides(edge, res, args)
    cfg = load_config(PAPER_CONFIG, overrides=overrides)
    tag = cache_tag(cfg)
    path = args.cache / f"paper-e{edge:g}-r{res:g}-{args.truth}-{tag}.npz"
    t = time.perf_counter()
    cached = path.is_file() and not args.rebuild
    if cached:
        problem = pipeline.load_problem(path, cfg)
    else:
        shift = cfg.synthetic.shift_mm
        for attempt in range(3):
            log(f"building the problem (edge {edge:g} mm, {res:g} mm images, {args.truth} truth, "
                f"shift {shift:g} mm): meshing and synthetic truth")
            try:
                trial = load_config(PAPER_CONFIG, overrides=overrides + [f"synthetic.shift_mm={shift:g}"])
                problem = pipeline.prepare(trial)
                break
            except ValueError as exc:
                if attempt == 2 or not any(w in str(exc) for w in ("inverted", "skull")):
                    raise
                log(f"  {exc}: again with half the shift")
                shift /= 2
        args.cache.mkdir(parents=True, exist_ok=True)
        pipeline.save_problem(problem, path)  # the posterior does not depend on the shift
    mesh, post = problem.mesh, problem.posterior
    truth_info = {k: v for k, v in (problem.truth_info or {}).items()
                  if not isinstance(v, (list, dict))}
    info = {
        "edge_length_mm": edge, "resolution_mm": res, "truth": args.truth, "truth_info": truth_info,
        "cache": str(path.name), "from_cache": cached, "load_or_build_s": time.perf_counter() - t,
        "build_timings_s": problem.timings,
        "nodes": len(mesh.nodes), "tets": len(mesh.tets), "boundary_nodes": len(mesh.boundary),
        "interior_dofs": 3 * post.op.n_interior, "dim": post.dim,
        "tets_per_tissue": np.bincount(mesh.tissue, minlength=3).tolist(),
    }
    return problem, cfg, info


def laplace_bytes(problem) -> float:
    """Rough peak bytes of :func:`bayesreg.pipeline.laplace_precision` (dense Jacobian, map)."""
    post = problem.posterior
    nb3, ni3, nq = 3 * post.n_boundary, 3 * post.op.n_interior, 4 * len(problem.mesh.tets)
    return 8.0 * (3 * nq * nb3 + 2 * ni3 * nb3 + 4 * nb3 * nb3)


def kernel_setup(problem, base_overrides: list[str], kernel: str, n_chains: int, args) -> dict:
    """Config, starts, jumping-kernel scales and CG preconditioners of one kernel.

    The starts and scales come from :func:`pipeline.initialise`; the CG preconditioner of each
    of ``--chains``' counts from :func:`pipeline.cg_preconditioner` for that count, so a row
    samples as ``sample`` would with that many chains (until stop 37 every row took the
    largest count's: block Jacobi for all of a run that went to 1,024 chains on a GPU).

    ``blocked-laplace`` needs the dense Gauss-Newton precision; where that would exceed
    ``--laplace-max-gb`` a *surrogate* dense factor ``diag(sigma_u)`` of the same shape is used
    (the same arithmetic per step, not the same acceptance) and the result says so.
    """
    surrogate = kernel.startswith("blocked-laplace") and laplace_bytes(problem) > args.laplace_max_gb * 2**30
    kernel_overrides = KERNELS[kernel]
    if surrogate:
        kernel_overrides = [o.replace("proposal=laplace", "proposal=isotropic") for o in kernel_overrides]
    cfg = load_config(PAPER_CONFIG, overrides=base_overrides + kernel_overrides
                      + [f"sampler.chains={max(2, n_chains)}",
                         f"solver.preconditioner={args.preconditioner}"])
    t = time.perf_counter()
    init = pipeline.initialise(problem, cfg)
    sigma = tuple(np.asarray(s) for s in init.sigma)
    if surrogate:
        sigma = (np.diag(sigma[0]), sigma[1])
    nb3 = 3 * problem.posterior.n_boundary
    dim = problem.posterior.dim
    blocks = (np.arange(nb3), np.arange(nb3, dim)) if init.blocked else None
    condensation = None
    if init.blocked and cfg.sampler.use_condensed:  # as bayesreg.pipeline.sample_problem builds it
        condensation = pipeline._condensed_rw(problem, cfg)
    # each chain count's CG preconditioner, as `sample` picks it for that many chains (`auto`
    # gives up the dense inverses where the chains' copies would not fit the device's budget)
    by_chains = {c: pipeline.cg_preconditioner(problem, cfg, n_chains=c) for c in args.chain_counts}
    preconditioner = pipeline._preconditioner_rw(problem, cfg) if "dense" in by_chains.values() else None
    return {"cfg": cfg, "x0": np.asarray(init.x0), "sigma": sigma, "blocks": blocks,
            "condensation": condensation, "preconditioner": preconditioner,
            # the fewest chains' (figure 2's pieces) and each chain count's (figure 3's rows)
            "cg_preconditioner": by_chains[min(by_chains)], "cg_preconditioner_by_chains": by_chains,
            "n_blocks": 1 if blocks is None else len(blocks), "surrogate_factor": surrogate,
            # CG solves per step: one per block, but condensed u_b moves take no CG solve
            "cg_solves": (1 if blocks is None else len(blocks)) - (condensation is not None),
            "initialise_s": time.perf_counter() - t}


# ---------------------------------------------------------------------------------------------
# 1. log-density evaluations
# ---------------------------------------------------------------------------------------------

def bench_logdensity(problem, cfg, x0, sigma_joint, chains, args) -> list[dict]:
    """Evaluations/s of ``jit(vmap(logdensity))`` over ``C`` positions, cold and warm."""
    logdensity = pipeline.make_logdensity(problem, cfg)
    n_i = problem.posterior.op.n_interior
    f = jax.jit(jax.vmap(logdensity))
    rng = np.random.default_rng(1)
    rows = []
    for c in chains:
        row = {"chains": c}
        try:
            x = jnp.asarray(x0[np.arange(c) % len(x0)])
            cold0 = jnp.zeros((c, n_i, 3))
            lp, aux = block(f(x, cold0))
            x2 = x + jnp.asarray(sigma_joint * rng.standard_normal(x.shape))
            for name, pos, guess in (("cold", x, cold0), ("warm", x2, aux.interior)):
                t = time_call(f, pos, guess, target_s=args.time_target_s)
                lp2, aux2 = f(pos, guess)
                it = np.asarray(aux2.solve.iterations)
                row[name] = {"evals_per_s": c / t["mean_s"], "ms_per_call": 1e3 * t["mean_s"],
                             "cg_iterations_mean": float(it.mean()), "cg_iterations_max": int(it.max()),
                             "finite": int(np.isfinite(np.asarray(lp2)).sum()),
                             "compile_s": t["warmup_incl_compile_s"]}
        except Exception as exc:  # noqa: BLE001 - e.g. device memory at large C
            row["error"] = f"{type(exc).__name__}: {exc}"
            log(f"  log-density C={c}: {row['error']}")
        rows.append(row)
        if "error" not in row:
            log(f"  log-density C={c}: cold {row['cold']['evals_per_s']:.0f}/s "
                f"(CG {row['cold']['cg_iterations_mean']:.0f}), warm {row['warm']['evals_per_s']:.0f}/s "
                f"(CG {row['warm']['cg_iterations_mean']:.0f})")
    return rows


# ---------------------------------------------------------------------------------------------
# 2. time split
# ---------------------------------------------------------------------------------------------

def _in_scan(fn):
    """Jitted ``xs -> sum_k fn(xs[k])`` as one ``lax.scan``: the per-item cost inside a loop,
    as in the sampler (no dispatch per item; each item's input differs, so nothing is hoisted)."""

    @jax.jit
    def run(xs):
        return jax.lax.scan(lambda acc, x: (acc + fn(x), None), jnp.zeros(()), xs)[0]

    return run


def bench_split(problem, cfg, x, setups, args, n_items: int = 20) -> dict:
    """Solve, similarity, whole log-density and proposal, each jitted and timed alone.

    Each piece runs ``n_items`` times inside one ``lax.scan`` on inputs that differ by a
    tiny jitter (``1e-9`` of the kernel's scale), and the time per item is reported.  The
    solves and the log-density use the paper-joint sampler's CG preconditioner for the run's
    fewest chains (dense ``K_ii^-1`` built once at ``x``, as a chain builds it at each chunk
    start; spectral or block Jacobi otherwise), so that they are the pieces of its MH step;
    the dense inverse's build is timed as a piece of its own (once per chunk, not per step).
    """
    post = problem.posterior
    rtol, maxiter = cfg.solver.rtol, cfg.solver.maxiter
    zeros = jnp.zeros((post.op.n_interior, 3))
    joint = setups["paper-joint"]
    joint_sigma = joint["sigma"][0]
    rng = np.random.default_rng(2)
    x = np.asarray(x)
    x2 = x + joint_sigma * rng.standard_normal(x.shape)  # one paper-kernel move away

    def jitter(a, scale):
        return jnp.asarray(a[None] + 1e-9 * scale * rng.standard_normal((n_items,) + a.shape))

    build = None if joint["preconditioner"] is None else joint["preconditioner"].build
    precond = None if build is None else block(jax.jit(build)(jnp.asarray(x)))

    def solve(theta, guess):
        u_b, phi = split_position(post, theta)
        lam_g, mu_g = elastic_groups(post, phi)
        return solve_interior_blocks(post.op, *stiffness_blocks(post, lam_g, mu_g), u_b, guess,
                                     rtol=rtol, maxiter=maxiter,
                                     precond=_precond_at(post, precond, lam_g, mu_g))

    u_i, _ = block(jax.jit(solve)(jnp.asarray(x), zeros))
    u = np.asarray(full_displacement(post, split_position(post, jnp.asarray(x))[0], u_i))
    pieces = {
        "solve_cold": (lambda th: jnp.sum(solve(th, zeros)[0]), jitter(x, joint_sigma)),
        "solve_warm": (lambda th: jnp.sum(solve(th, u_i)[0]), jitter(x2, joint_sigma)),
        "similarity": (lambda uu: ssd(post.ssd, uu[post.tets]), jitter(u, 1.0)),
        "logdensity_warm": (lambda th: log_density(post, th, u_i, rtol=rtol, maxiter=maxiter,
                                                   precond=precond)[0],
                            jitter(x2, joint_sigma)),
    }
    if build is not None:
        pieces["preconditioner_build"] = (lambda th: jnp.sum(build(th).inverse), jitter(x, joint_sigma))
    out = {"preconditioner": joint["cg_preconditioner"]}
    for name, (fn, xs) in pieces.items():
        t = time_call(_in_scan(fn), xs, target_s=args.time_target_s)
        out[name] = {"ms": 1e3 * t["mean_s"] / n_items}
    for name, theta, guess in (("solve_cold", x, zeros), ("solve_warm", x2, u_i)):
        out[name]["cg_iterations"] = int(jax.jit(solve)(jnp.asarray(theta), guess)[1].iterations)
    keys = jax.random.split(jax.random.key(3), 5 * n_items)
    for kernel, setup in setups.items():
        sig = tuple(jnp.asarray(s) for s in setup["sigma"])

        def draw(key, sig=sig):
            parts = []
            for s_, k_ in zip(sig, jax.random.split(key, len(sig))):
                z = jax.random.normal(k_, (s_.shape[0],))
                parts.append(s_ @ z if s_.ndim == 2 else s_ * z)
            return jnp.sum(jnp.concatenate(parts))

        t = time_call(_in_scan(draw), keys, target_s=args.time_target_s)
        out[f"proposal_{kernel}"] = {"ms": 1e3 * t["mean_s"] / len(keys),
                                     "factor_shape": [list(np.shape(s)) for s in setup["sigma"]]}
    log(f"  split ({out['preconditioner']} CG): "
        + ", ".join(f"{k} {v['ms']:.3g} ms" for k, v in out.items() if isinstance(v, dict)))
    return out


# ---------------------------------------------------------------------------------------------
# 3. MH steps
# ---------------------------------------------------------------------------------------------

def _mean_chunk_s(stamps: list[float]) -> float:
    """Mean seconds of the timed chunks, from the time stamps at the chunks' ends (the first
    stamp ends the compiling chunk): the profiled chunk's expected length."""
    return (stamps[-1] - stamps[0]) / (len(stamps) - 1)


def _plain_run(logdensity, x0, interior0, sigma, blocks, chunk_draws, n_chunks, key, condensation=None,
               preconditioner=None, warmup_steps=0, profiler=None):
    """The sampler's kernel (:func:`bayesreg.sampler.build_kernel`) in a plain jitted ``scan``.

    Used for one chain (``sample`` needs two or more, for R-hat): the chain is not vmapped,
    as ``sample`` runs one chain per device.  With ``C > 1`` the chains are vmapped on one
    device (the layout ``sample`` replaces by sharding).  A kernel with a cache (condensation,
    preconditioner) builds it at each chunk start, as ``sample`` does.  No warm-up: a
    ``warmup_steps`` other than 0 is an error (``sample`` tunes the scales, this runner cannot).
    With a ``profiler`` (:class:`profiling.ChunkProfiler`), one more chunk runs under it
    after the ``n_chunks`` (its time stamp is the last; its figures are not in the others).
    """
    if warmup_steps:
        raise ValueError("--warmup-steps needs sample(): two chains or more")
    from bayesreg.sampler import build_kernel, init

    sig = tuple(jnp.asarray(s) for s in sigma)
    steps = chunk_draws * THINNING
    kernel = build_kernel(logdensity, blocks, condensation, preconditioner)
    if not hasattr(kernel, "init_cache"):
        def one_chain(key, state):
            return jax.lax.scan(lambda st, k: kernel(k, st, sig), state, jax.random.split(key, steps))
    else:  # the kernel carries the cache: (key, state, sigmas, cache) -> (state, info, cache)
        def one_chain(key, state):
            def step(carry, k):
                st, info, cache = kernel(k, carry[0], sig, carry[1])
                return (st, cache), info

            carry, info = jax.lax.scan(step, (state, kernel.init_cache(state)),
                                       jax.random.split(key, steps))
            return carry[0], info

    n = len(x0)
    if n == 1:
        chunk = jax.jit(lambda keys, st: one_chain(keys[0], st))
        state = jax.jit(lambda x: init(x, logdensity, interior0))(jnp.asarray(x0[0]))
    else:
        chunk = jax.jit(jax.vmap(one_chain))
        state = jax.jit(jax.vmap(lambda x: init(x, logdensity, interior0)))(jnp.asarray(x0))
    stamps, acc, cg, fail = [], [], [], []
    for k in range(n_chunks + (profiler is not None)):
        if k == n_chunks:
            profiler.start(expected_s=_mean_chunk_s(stamps))
        state, info = chunk(jax.random.split(jax.random.fold_in(key, k), n), state)
        block(state)
        stamps.append(time.perf_counter())
        if k == n_chunks:
            profiler.stop()
        elif k:
            a = np.asarray(info.acceptance_rate)
            acc.append(a.reshape(-1, a.shape[-1]).mean(axis=0))
            cg.append(float(np.asarray(info.cg_iterations).mean()))
            fail.append(int(np.asarray(info.solve_failed).sum()))
    how = "build_kernel in a jitted scan" + (" (vmapped chains)" if n > 1 else " (one chain)")
    return stamps, np.mean(acc, axis=0), float(np.mean(cg)), int(np.sum(fail)), how


def _sample_run(logdensity, x0, interior0, sigma, blocks, chunk_draws, n_chunks, key, condensation=None,
                preconditioner=None, warmup_steps=0, profiler=None):
    """``bayesreg.sampler.sample`` with a fixed number of draws after ``warmup_steps`` (tuning
    the scales, not timed); time stamps per chunk.  With a ``profiler``
    (:class:`profiling.ChunkProfiler`), one more chunk runs under it after the ``n_chunks``
    (its time stamp is the last; its acceptance and CG figures are not in the others)."""
    stamps: list[float] = []
    total = n_chunks + (profiler is not None)

    def on_chunk(_ckpt, out):
        if out is not None:
            stamps.append(time.perf_counter())
            if profiler is not None and len(stamps) == n_chunks:
                profiler.start(expected_s=_mean_chunk_s(stamps))

    kw = dict(blocks=blocks, thinning=THINNING, warmup_steps=warmup_steps, max_draws=total * chunk_draws,
              min_draws=total * chunk_draws, chunk_draws=chunk_draws, progress=False,
              rhat_threshold=1.2)
    if condensation is not None:
        kw["condensation"] = condensation
    if preconditioner is not None:
        kw["preconditioner"] = preconditioner
    try:
        res = sample(key, logdensity, x0, interior0, sigma, on_chunk=on_chunk, **kw)
    finally:
        if profiler is not None:
            profiler.stop()
    how = "sample(), on_chunk time stamps"
    timed = slice(chunk_draws, n_chunks * chunk_draws)
    acc = np.asarray(res.acceptance)[:, timed].reshape(-1, np.shape(res.acceptance)[-1]).mean(axis=0)
    cg = float(np.asarray(res.cg_iterations)[:, timed].mean())
    fail = int(np.asarray(res.solve_failures)[:, timed].sum())
    return stamps, acc, cg, fail, how


def bench_sampler(problem, setup, chains, evals, args, kernel, build_s=None, mesh="mesh") -> list[dict]:
    """MH steps/s per chain and in total for each chain count (one kernel).

    ``sample`` for two chains or more, :func:`_plain_run` for one; with ``--compare-vmap`` also
    :func:`_plain_run` (every chain vmapped on one device) for two or more, as extra rows.

    The chunks are sized to last about ``--chunk-seconds``, from the larger of two estimates
    of a chain's steps/s: figure 1's (``jit(vmap(logdensity))``, block-Jacobi CG unless the
    posterior has a spectral preconditioner) and the total of the kernel's previous chain
    count divided by ``C`` (on a CPU the chains share the cores, and figure 1's vmapped
    batches ran 1.2-3x slower per evaluation than one position at a time: sized from it alone,
    16 chains of the paper's size ran chunks of 10 steps).  Where the kernel builds a cache
    per chunk (``build_s``: one chain's dense ``K_ii^-1``, seconds), a chunk has at least
    :data:`AMORTISE_BUILD` times the steps one chain runs in that time, and such
    lengthened chunks are timed once (``timed_chunks`` in the row).  Each row samples with
    its own chain count's CG preconditioner (``cg_preconditioner`` in the row; the dense
    ``K_ii^-1`` and ``build_s`` only where that is ``dense``).  ``mesh`` names the
    mesh in the folders of ``--keep-profiles``.
    """
    logdensity = pipeline.make_logdensity(problem, setup["cfg"])
    interior0 = jnp.zeros((problem.posterior.op.n_interior, 3))
    post = problem.posterior
    rows = []
    runs = [(c, _sample_run if c >= 2 else _plain_run) for c in chains]
    if args.compare_vmap:
        runs += [(c, _plain_run) for c in chains if c >= 2]
    ev1 = next((e for e in evals if e["chains"] == 1 and "warm" in e), None)
    for c, runner in runs:
        row = {"kernel": kernel, "chains": c, "runner": "sample" if runner is _sample_run else "plain"}
        cg_name = setup["cg_preconditioner_by_chains"][c]
        dense = cg_name == "dense"
        try:
            ev = next((e for e in evals if e["chains"] == c and "warm" in e), None)
            rate = ev["warm"]["evals_per_s"] / c / setup["n_blocks"] if ev else 10.0
            done = [r for r in rows if "steps_per_s_total" in r]
            if done:
                rate = max(rate, done[-1]["steps_per_s_total"] / c)
            # the draws' positions and interiors are kept on the host: at most ~2 GB of them (for
            # the most chunks this row may run, the profiled one included)
            per_draw = 8 * c * (2 + args.timed_chunks) * (3 * post.op.n_interior + post.dim)
            cap = max(1, int(2 * 2**30 // per_draw))
            # --chunk-draws: a fixed window, acceptance comparable across chain counts
            wanted = args.chunk_draws or round(args.chunk_seconds * rate / THINNING)
            floor = 1
            if dense and build_s and not args.chunk_draws:
                # one chain's steps/s alone: the 1-chain row, else figure 1 at one position
                single = next((r["steps_per_s_per_chain"] for r in done if r["chains"] == 1),
                              ev1["warm"]["evals_per_s"] / setup["n_blocks"] if ev1 else rate)
                floor = math.ceil(AMORTISE_BUILD * build_s * single / THINNING)
            chunk_draws = int(np.clip(max(wanted, floor), 1, min(1000, cap)))
            timed_chunks = args.timed_chunks if chunk_draws <= wanted else 1
            n_chunks = 1 + timed_chunks
            x0 = setup["x0"][np.arange(c) % len(setup["x0"])]
            profiler = (None if args.no_split_profile
                        else profiling.ChunkProfiler(HLO_DUMP, max_seconds=args.split_profile_seconds,
                                                     on_begin=profile_memory_begin))
            t0 = time.perf_counter()
            try:
                stamps, acc, cg, fail, how = runner(logdensity, x0, interior0, setup["sigma"], setup["blocks"],
                                                    chunk_draws, n_chunks, jax.random.key(4),
                                                    condensation=setup["condensation"],
                                                    preconditioner=setup["preconditioner"] if dense else None,
                                                    warmup_steps=args.warmup_steps, profiler=profiler)
                wall = stamps[n_chunks - 1] - t0  # the chunks before the profiled one
                if profiler is not None:
                    # the extra chunk, after the timed ones: the step's parts where they ran
                    chunk_s = stamps[n_chunks] - stamps[n_chunks - 1]
                    try:
                        split = profiler.split(c * chunk_draws * THINNING, c * chunk_draws * THINNING / chunk_s)
                        # a whole profiled chunk: its own length (on a GPU the chunk's time stamps
                        # also hold the profiler's start, seconds of CUPTI's set-up)
                        length = chunk_s if split["steps_estimated"] else split["window_s"]
                        split["wall_ms_per_step_per_chain"] = 1e3 * length / (chunk_draws * THINNING)
                        row["split_profiled"] = split
                    except RuntimeError as exc:  # keep the row's other figures
                        row["split_profiled_error"] = str(exc)
                        log(f"    profiled chunk: {exc}")
            finally:
                if profiler is not None:
                    profiler.close(keep=None if args.keep_profiles is None else
                                   args.keep_profiles / f"{mesh}-{kernel}-C{c}-{row['runner']}")
                    profile_memory_end()
            seconds = stamps[n_chunks - 1] - stamps[0]
            row["warmup_steps"] = args.warmup_steps
            steps = timed_chunks * chunk_draws * THINNING
            per_chain = steps / seconds
            row.update({
                "steps_per_s_per_chain": per_chain, "steps_per_s_total": per_chain * c,
                "vs_paper_5_per_s": per_chain / PAPER_STEPS_PER_S,
                "timed_seconds": seconds, "timed_steps_per_chain": steps, "chunk_draws": chunk_draws,
                "timed_chunks": timed_chunks, "chunk_build_s": build_s if dense else None,
                "first_chunk_incl_compile_s": wall - seconds, "acceptance": acc.tolist(),
                "cg_iterations_per_step": cg, "cg_iterations_per_solve": cg / setup["cg_solves"],
                "solve_failures": fail, "how": how, "surrogate_factor": setup["surrogate_factor"],
                "cg_preconditioner": cg_name,
            })
            log(f"  {kernel} C={c} ({how}): {per_chain:.1f} steps/s per chain, {per_chain * c:.1f} total, "
                f"acc {np.round(acc, 2).tolist()}, CG/solve {cg / setup['cg_solves']:.0f} ({seconds:.1f} s timed)")
            if "split_profiled" in row:
                sp = row["split_profiled"]
                log("    profiled chunk: " + ", ".join(f"{k} {100 * v:.0f}%" for k, v in sp["share"].items() if v >= 0.005)
                    + f" of {sp['op_ms_per_step_total']:.3g} ms of operations per step (busy {sp['busy']:.2f})")
        except Exception as exc:  # noqa: BLE001 - keep the other figures
            row["error"] = f"{type(exc).__name__}: {exc}"
            log(f"  {kernel} C={c}: {row['error']}")
            traceback.print_exc()
        rows.append(row)
    return rows


# ---------------------------------------------------------------------------------------------
# 4. NumPy/SciPy reference
# ---------------------------------------------------------------------------------------------

def bench_reference(problem, cfg, setup, args) -> dict:
    """Log-density agreement with JAX, then the reference's joint-kernel MH steps/s."""
    t = time.perf_counter()
    ref = ReferencePosterior(problem, cfg)
    setup_s = time.perf_counter() - t
    post = problem.posterior
    zeros = jnp.zeros((post.op.n_interior, 3))
    loose = jax.jit(lambda th: log_density(post, th, zeros, rtol=cfg.solver.rtol,
                                           maxiter=cfg.solver.maxiter)[0])
    tight = jax.jit(lambda th: log_density(post, th, zeros, rtol=1e-13, maxiter=50 * cfg.solver.maxiter)[0])
    sigma = setup["sigma"][0]
    rng = np.random.default_rng(5)
    checks = []
    for x in setup["x0"][:3]:
        for theta in (x, x + sigma * rng.standard_normal(x.shape)):
            r = ref(theta)
            a, b = float(loose(jnp.asarray(theta))), float(tight(jnp.asarray(theta)))
            checks.append({"reference": r, "jax": a, "jax_tight": b,
                           "rel_diff": abs(a - r) / abs(r) if np.isfinite(r) else None,
                           "rel_diff_tight": abs(b - r) / abs(r) if np.isfinite(r) else None})
    finite = [c for c in checks if c["rel_diff"] is not None]
    out = {
        "setup_s": setup_s, "positions": len(checks), "finite_positions": len(finite),
        "max_rel_diff": max((c["rel_diff"] for c in finite), default=None),
        "max_rel_diff_tight": max((c["rel_diff_tight"] for c in finite), default=None),
        "both_infinite_agree": all(np.isfinite(c["reference"]) == np.isfinite(c["jax"]) for c in checks),
        "checks": checks,
    }
    out["agrees"] = bool(out["both_infinite_agree"] and out["max_rel_diff_tight"] is not None
                         and out["max_rel_diff_tight"] < 1e-8)
    log(f"  reference vs JAX log-density: max rel diff {out['max_rel_diff']:.2e} (CG rtol "
        f"{cfg.solver.rtol:g}), {out['max_rel_diff_tight']:.2e} (rtol 1e-13)"
        + ("" if out["agrees"] else "   <-- DISCREPANCY"))
    out["mh"] = reference_mh(ref, setup["x0"][0], sigma, 10**6, max_seconds=args.reference_seconds)
    out["mh"]["permc_spec"] = ref.permc_spec
    log(f"  reference MH (paper-joint, 1 chain): {out['mh']['steps_per_s']:.1f} steps/s "
        f"(factor {out['mh']['factor_ms_per_step']:.2f} ms, solve {out['mh']['solve_ms_per_step']:.2f} ms, "
        f"SSD {out['mh']['ssd_ms_per_step']:.2f} ms per step)")
    return out


# ---------------------------------------------------------------------------------------------
# quickstart
# ---------------------------------------------------------------------------------------------

def bench_quickstart(overrides: list[str]) -> dict:
    """Run the quickstart job; wall time, ESS/s of the slowest estimand, time to R-hat < 1.2."""
    import bayesreg

    with tempfile.TemporaryDirectory() as tmp:
        t = time.perf_counter()
        res = bayesreg.run(str(QUICKSTART_CONFIG), out=Path(tmp) / "qs", progress=False,
                           overrides=overrides or None)
        wall = time.perf_counter() - t
        info = res.info
    s, tm = info["sampler"], info["timings_s"]
    thr = s["rhat_threshold"]
    draws = s["draws_per_chain"]
    first = next((d for d, r in s["rhat_history"] if r < thr), None)
    sampling = tm.get("sampling_s", float("nan"))
    before = tm.get("total_before_outputs_s", wall)
    out = {
        "overrides": overrides, "wall_s": wall, "timings_s": tm, "chains": s["chains"],
        "draws_per_chain": draws, "steps_per_chain": s["steps_per_chain"],
        "steps_per_s_per_chain": s["steps_per_s_per_chain"], "converged": s["converged"],
        "ess_bulk_min": s["ess_bulk_min"], "ess_bulk_min_per_sampling_s": s["ess_bulk_min"] / sampling,
        "rhat_classic_max": s["rhat_classic_max"], "rhat_threshold": thr,
        "rhat_below_threshold_at_draws": first,
        # sampling runs at a steady rate: interpolate the wall time at that draw
        "rhat_below_threshold_wall_s": (before - sampling * (1 - first / draws)) if first else None,
        "acceptance": s["acceptance"], "mesh_nodes": info["mesh"].get("n_nodes"),
    }
    log(f"quickstart: {wall:.0f} s wall, {draws} draws x {s['chains']} chains, converged "
        f"{s['converged']}, min bulk ESS {s['ess_bulk_min']:.1f} ({out['ess_bulk_min_per_sampling_s']:.3f}/s), "
        f"R-hat < {thr} at draws {first}")
    return out


# ---------------------------------------------------------------------------------------------
# report
# ---------------------------------------------------------------------------------------------

def _f(x, fmt="{:.3g}"):
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return "-"
    return fmt.format(x)


def markdown(res: dict) -> str:
    m = res["machine"]
    lines = [f"# bayesreg speed benchmark ({res['profile']})", "",
             f"{res['started_utc']}, `{' '.join(res['command'])}`, {res['total_s']:.0f} s", "",
             "| machine | |", "|---|---|"]
    for k in ("cpu_model", "cores_available", "memory_gib", "load_average_at_start", "backend",
              "devices", "jax", "jaxlib", "xla_flags", "git_commit", "git_dirty"):
        lines.append(f"| {k} | {m.get(k)} |")
    meshes = res["meshes"]
    lines += ["", "## Meshes", "",
              "| edge mm | image mm | nodes | tets | boundary nodes | interior DOFs | dim | meshing s | from cache |",
              "|---|---|---|---|---|---|---|---|---|"]
    for r in meshes:
        p = r["problem"]
        lines.append(f"| {p['edge_length_mm']:g} | {p['resolution_mm']:g} | {p['nodes']} | {p['tets']} | "
                     f"{p['boundary_nodes']} | {p['interior_dofs']} | {p['dim']} | "
                     f"{_f(p['build_timings_s'].get('mesh_s'), '{:.1f}')} | {p['from_cache']} |")

    lines += ["", "## Log-density evaluations (`jit(vmap(logdensity))` over C positions)", "",
              "| nodes | C | cold evals/s | warm evals/s | CG cold mean / max | CG warm mean / max |",
              "|---|---|---|---|---|---|"]
    for r in meshes:
        for e in r.get("logdensity", []):
            if "error" in e:
                lines.append(f"| {r['problem']['nodes']} | {e['chains']} | {e['error']} | | | |")
                continue
            c, w = e["cold"], e["warm"]
            lines.append(f"| {r['problem']['nodes']} | {e['chains']} | {c['evals_per_s']:.1f} | {w['evals_per_s']:.1f} | "
                         f"{c['cg_iterations_mean']:.0f} / {c['cg_iterations_max']} | "
                         f"{w['cg_iterations_mean']:.0f} / {w['cg_iterations_max']} |")

    lines += ["", "## The pieces of a step, each timed alone (single position, ms)", "",
              "| nodes | CG preconditioner (its build, once per chunk) | solve cold (CG it) | "
              "solve warm (CG it) | similarity | log-density warm | "
              "proposal paper-joint | proposal blocked-laplace | paper-joint MH step (1 chain) |",
              "|---|---|---|---|---|---|---|---|---|"]
    for r in meshes:
        s = r.get("split")
        if not s:
            continue
        step = next((x for x in r.get("sampler", []) if x["kernel"] == "paper-joint"
                     and x["chains"] == 1 and "error" not in x), None)
        step_ms = 1e3 / step["steps_per_s_per_chain"] if step else None
        lap = s.get("proposal_blocked-laplace", {}).get("ms")
        pre = s.get("preconditioner", "block-jacobi")  # (results before 2026-11-26 timed block Jacobi)
        if "preconditioner_build" in s:
            pre += f" ({s['preconditioner_build']['ms']:.3g})"
        lines.append(f"| {r['problem']['nodes']} | {pre} | {s['solve_cold']['ms']:.3g} ({s['solve_cold']['cg_iterations']}) | "
                     f"{s['solve_warm']['ms']:.3g} ({s['solve_warm']['cg_iterations']}) | {s['similarity']['ms']:.3g} | "
                     f"{s['logdensity_warm']['ms']:.3g} | {s['proposal_paper-joint']['ms']:.3g} | {_f(lap)} | "
                     f"{_f(step_ms)} |")

    names = profiling.order()
    lines += ["", "## Time split inside the sampler (one profiled chunk after the timed ones; "
                  "ms per MH step summed over threads, share)", "",
              "| nodes | kernel | C | " + " | ".join(names) + " | all operations | "
              "wall ms per step per chain (profiled / timed) | busy (s of operations per s) |",
              "|---|---|---|" + "---|" * len(names) + "---|---|---|"]
    for r in meshes:
        for x in r.get("sampler", []):
            sp = x.get("split_profiled")
            if not sp or "error" in x:
                continue
            cells = [f"{sp['ms_per_step'][k]:.3g} ({100 * sp['share'].get(k, 0):.0f}%)" for k in names]
            lines.append(f"| {r['problem']['nodes']} | {x['kernel']} | {x['chains']} | " + " | ".join(cells)
                         + f" | {sp['op_ms_per_step_total']:.3g} | {sp['wall_ms_per_step_per_chain']:.3g} / "
                         f"{1e3 / x['steps_per_s_per_chain']:.3g} | "
                         + (f"{sp['busy']:.2f} |" if "busy" in sp else "|"))

    lines += ["", "## MH steps per second (`bayesreg.sampler.sample`, thinning 10, compile excluded)", "",
              "| nodes | kernel | C | steps/s per chain | steps/s total | x paper (5/s per chain) | "
              "acceptance | CG per solve | steps per chunk x timed chunks | timed s |",
              "|---|---|---|---|---|---|---|---|---|---|"]
    for r in meshes:
        for x in r.get("sampler", []):
            name = x["kernel"] + (" (surrogate factor)" if x.get("surrogate_factor") else "")
            name += f", {x['cg_preconditioner']} CG" if x.get("cg_preconditioner") else ""
            name += f", after {x['warmup_steps']:,} warm-up steps" if x.get("warmup_steps") else ""
            if x.get("runner") == "plain" and x["chains"] > 1:
                name += " (plain vmap, not sample)"
            if "error" in x:
                lines.append(f"| {r['problem']['nodes']} | {name} | {x['chains']} | {x['error']} | | | | | | |")
                continue
            lines.append(f"| {r['problem']['nodes']} | {name} | {x['chains']} | {x['steps_per_s_per_chain']:.1f} | "
                         f"{x['steps_per_s_total']:.1f} | {x['vs_paper_5_per_s']:.1f} | "
                         f"{' / '.join(f'{a:.2f}' for a in x['acceptance'])} | "
                         f"{x['cg_iterations_per_solve']:.0f} | "
                         f"{x['chunk_draws'] * THINNING} x {x.get('timed_chunks', '-')} | {x['timed_seconds']:.1f} |")

    if any(r.get("reference") for r in meshes):
        lines += ["", "## NumPy/SciPy reference (paper-joint kernel, 1 chain)", "",
                  "| nodes | max rel. diff of log p (CG rtol cfg / 1e-13) | ref steps/s | ref factor / solve / SSD ms per step | "
                  "JAX steps/s (1 chain) | JAX / reference |",
                  "|---|---|---|---|---|---|"]
        for r in meshes:
            ref = r.get("reference")
            if not ref:
                continue
            if "error" in ref:
                lines.append(f"| {r['problem']['nodes']} | {ref['error']} | | | | |")
                continue
            mh = ref["mh"]
            jx = next((x for x in r.get("sampler", []) if x["kernel"] == "paper-joint" and "error" not in x), None)
            jx_rate = jx["steps_per_s_per_chain"] if jx else None
            c_note = f" (C={jx['chains']})" if jx and jx["chains"] != 1 else ""
            lines.append(f"| {r['problem']['nodes']} | {_f(ref['max_rel_diff'], '{:.1e}')} / "
                         f"{_f(ref['max_rel_diff_tight'], '{:.1e}')}{'' if ref['agrees'] else ' DISCREPANCY'} | "
                         f"{mh['steps_per_s']:.1f} | {mh['factor_ms_per_step']:.2f} / {mh['solve_ms_per_step']:.2f} / "
                         f"{mh['ssd_ms_per_step']:.2f} | {_f(jx_rate, '{:.1f}')}{c_note} | "
                         f"{_f(jx_rate / mh['steps_per_s'] if jx_rate else None, '{:.2f}')} |")

    q = res.get("quickstart")
    if q:
        lines += ["", "## Quickstart (`configs/quickstart.yaml`)", "", "| | |", "|---|---|"]
        if "error" in q:
            lines.append(f"| error | {q['error']} |")
        else:
            rows = [("wall s", f"{q['wall_s']:.0f}"), ("chains x draws (thinning 10)", f"{q['chains']} x {q['draws_per_chain']}"),
                    ("steps/s per chain", f"{q['steps_per_s_per_chain']:.1f}"),
                    ("warm-up s / sampling s", f"{_f(q['timings_s'].get('warmup_s'), '{:.0f}')} / "
                                               f"{_f(q['timings_s'].get('sampling_s'), '{:.0f}')}"),
                    ("converged (classic R-hat < threshold)", str(q["converged"])),
                    ("max classic R-hat", f"{q['rhat_classic_max']:.3f}"),
                    ("min bulk ESS", f"{q['ess_bulk_min']:.1f}"),
                    ("min bulk ESS per sampling second", f"{q['ess_bulk_min_per_sampling_s']:.4f}"),
                    ("R-hat < 1.2 first at draws / wall s", f"{_f(q['rhat_below_threshold_at_draws'], '{}')} / "
                                                            f"{_f(q['rhat_below_threshold_wall_s'], '{:.0f}')}")]
            if q["overrides"]:
                rows.insert(0, ("overrides", " ".join(q["overrides"])))
            lines += [f"| {a} | {b} |" for a, b in rows]

    lines += ["", "## Peak memory", "", "| after | peak RSS MiB | device peak MiB |", "|---|---|---|"]
    for snap in res["memory"]:
        dev = snap.get("device") or {}
        peak = dev.get("peak_bytes_in_use")
        lines.append(f"| {snap['phase']} | {snap['peak_rss_mib']:.0f} | {_f(peak / 2**20 if peak else None, '{:.0f}')} |")
    return "\n".join(lines) + "\n"


# ---------------------------------------------------------------------------------------------
# main
# ---------------------------------------------------------------------------------------------

def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--quick", action="store_true", help="one coarse mesh (26 mm, 3 mm images), short timings")
    p.add_argument("--meshes", help="comma-separated EDGE[@RESOLUTION] in mm (default 16,10,7; quick 26@3)")
    p.add_argument("--chains", default="1,3,16,64", help="comma-separated chain counts (default 1,3,16,64)")
    p.add_argument("--kernels", default=",".join(DEFAULT_KERNELS),
                   help=f"comma-separated, of {', '.join(KERNELS)} (default {','.join(DEFAULT_KERNELS)})")
    p.add_argument("--out", type=Path, default=REPO / "benchmarks" / "results")
    p.add_argument("--cache", type=Path, default=REPO / "benchmarks" / ".cache")
    p.add_argument("--rebuild", action="store_true", help="re-mesh even if a cached problem exists")
    p.add_argument("--truth", choices=("constrained", "smooth"), default="smooth",
                   help="synthetic truth of the problems: smooth (default, seconds to build) or "
                        "constrained (the paper's Sec. 4.1; dense in the boundary nodes, did not "
                        "finish in 30 CPU-minutes at 10k nodes)")
    p.add_argument("--shift-mm", type=float, default=None,
                   help="synthetic shift (default 7.5 mm with the smooth truth, the config's 15 mm "
                        "with the constrained one: 15 mm smooth inverts elements of fine meshes)")
    p.add_argument("--preconditioner", choices=("auto", "dense", "spectral", "block-jacobi"), default="auto",
                   help="solver.preconditioner of the sampler's solves (default auto, as the configs)")
    p.add_argument("--no-reference", action="store_true", help="skip the NumPy/SciPy reference")
    p.add_argument("--no-split-profile", action="store_true",
                   help="skip figure 2b (each sampler row's extra chunk run under jax.profiler)")
    p.add_argument("--split-profile-seconds", type=float, default=1.0,
                   help="profile at most this many seconds of figure 2b's chunk, a window a third of "
                        "the way into a longer one (the profiler holds every event in memory: about "
                        "1 kB each); on a GPU the whole chunk (--chunk-seconds), started and stopped "
                        "with the device idle")
    p.add_argument("--keep-profiles", type=Path, default=None, metavar="DIR",
                   help="keep figure 2b's traces in DIR/MESH-KERNEL-CCHAINS-RUNNER/ (TensorBoard's "
                        "profile plugin opens them) and the step's compiled HLO in DIR/hlo/")
    p.add_argument("--reference-max-nodes", type=int, default=10**9,
                   help="skip the reference on meshes with more nodes")
    p.add_argument("--laplace-max-gb", type=float, default=6.0,
                   help="above this estimated host memory for the Laplace precision, blocked-laplace "
                        "uses a surrogate dense factor of the same shape")
    p.add_argument("--compare-vmap", action="store_true",
                   help="also time every chain count >= 2 vmapped on one device (not through sample)")
    p.add_argument("--warmup-steps", type=int, default=0,
                   help="steps per chain of sample()'s warm-up (scales tuned, not timed) before the "
                        "timed chunks: the figures of a tuned chain (default 0: the starts' scales; "
                        "two chains or more)")
    p.add_argument("--chunk-draws", type=int, default=None,
                   help="draws per sampler chunk for every chain count, instead of --chunk-seconds: "
                        "the timed steps then cover the same part of every chain (untuned chains "
                        "change their acceptance as they leave their starts); capped like the "
                        "computed size (1000, and 2 GB of stored draws)")
    p.add_argument("--quickstart", action="store_true", help="also run configs/quickstart.yaml end to end")
    p.add_argument("--quickstart-set", action="append", default=[], metavar="KEY=VALUE",
                   help="override for the quickstart job (repeatable), e.g. sampler.max_draws=200")
    for name, help_ in (("chunk-seconds", "target duration of one sampler chunk"),
                        ("timed-chunks", "chunks timed after the compiling one"),
                        ("time-target-s", "time spent per timed function in figures 1-2"),
                        ("reference-seconds", "duration of the reference MH run")):
        p.add_argument(f"--{name}", type=float if name != "timed-chunks" else int, default=None, help=help_)
    args = p.parse_args(argv)
    prof = PROFILES["quick" if args.quick else "full"]
    for k, v in prof.items():
        if getattr(args, k, None) is None:
            setattr(args, k, v)
    if args.shift_mm is None and args.truth == "smooth":
        args.shift_mm = 7.5
    args.mesh_specs = [parse_mesh(s) for s in args.meshes.split(",") if s.strip()]
    args.chain_counts = sorted({int(c) for c in args.chains.split(",") if c.strip()})
    args.kernel_names = [k for k in args.kernels.split(",") if k]
    unknown = set(args.kernel_names) - set(KERNELS)
    if unknown:
        p.error(f"unknown kernels {sorted(unknown)}; choose from {list(KERNELS)}")
    if "paper-joint" not in args.kernel_names:
        args.kernel_names.insert(0, "paper-joint")  # its sigma drives the warm starts and the reference
    return args


def main(argv=None) -> dict:
    args = parse_args(argv)
    t_start = time.perf_counter()
    started = _dt.datetime.now(_dt.timezone.utc)
    machine = machine_info()
    log(f"{machine['cpu_model']}, {machine['cores_available']} cores, JAX {machine['jax']} "
        f"{machine['backend']} {machine['devices']}")
    res = {"profile": "quick" if args.quick else "full", "command": [Path(sys.argv[0]).name, *sys.argv[1:]],
           "started_utc": started.isoformat(timespec="seconds"), "machine": machine,
           "settings": {k: getattr(args, k) for k in ("chain_counts", "kernel_names", "chunk_seconds", "chunk_draws",
                                                        "timed_chunks", "time_target_s", "reference_seconds",
                                                        "truth", "shift_mm", "laplace_max_gb",
                                                        "no_split_profile", "split_profile_seconds")},
           "meshes": [], "memory": [memory_snapshot("start")]}
    # starts from initialise() for at most 16 chains, tiled to larger chain counts (its validity
    # check vmaps the log-density over every start: 1024 at once would not fit a GPU at 10k nodes)
    n_setup = max(2, min(max(args.chain_counts), 16))
    for edge, resolution in args.mesh_specs:
        log(f"mesh {edge:g} mm on {resolution:g} mm images")
        entry: dict = {}
        res["meshes"].append(entry)
        problem, cfg, entry["problem"] = build_problem(edge, resolution, args)
        p = entry["problem"]
        log(f"  {p['nodes']} nodes, {p['tets']} tets, {p['boundary_nodes']} boundary nodes "
            f"({'cache' if p['from_cache'] else 'built'} in {p['load_or_build_s']:.1f} s)")
        res["memory"].append(memory_snapshot(f"problem {p['nodes']} nodes"))
        base = mesh_overrides(edge, resolution, args)
        setups = {}
        for k in args.kernel_names:
            try:
                setups[k] = kernel_setup(problem, base, k, n_setup, args)
            except Exception as exc:  # noqa: BLE001
                entry.setdefault("errors", []).append(f"setup {k}: {type(exc).__name__}: {exc}")
                log(f"  setup {k}: {exc}")
        entry["kernels"] = {k: {"initialise_s": s["initialise_s"], "surrogate_factor": s["surrogate_factor"],
                                "blocks": s["n_blocks"], "cg_preconditioner": s["cg_preconditioner_by_chains"]}
                            for k, s in setups.items()}
        res["memory"].append(memory_snapshot(f"initialise {p['nodes']} nodes"))
        joint = setups["paper-joint"]
        entry["logdensity"] = bench_logdensity(problem, cfg, joint["x0"], joint["sigma"][0],
                                               args.chain_counts, args)
        res["memory"].append(memory_snapshot(f"log-density {p['nodes']} nodes"))
        entry["split"] = bench_split(problem, cfg, joint["x0"][0], setups, args)
        entry["sampler"] = []
        for k, s in setups.items():
            # each chain's chunk-start build of the dense K_ii^-1 (timed in the split; the opt-in
            # condensed kernel's per-chunk condensation is not timed, so not accounted for)
            build_ms = (entry["split"].get("preconditioner_build", {}).get("ms")
                        if s["preconditioner"] is not None else None)
            build_s = build_ms / 1e3 if build_ms else None
            entry["sampler"] += bench_sampler(problem, s, args.chain_counts, entry["logdensity"], args, k,
                                              build_s=build_s, mesh=f"{p['nodes']}nodes")
            res["memory"].append(memory_snapshot(f"sampler {k} {p['nodes']} nodes"))
        if not args.no_reference and p["nodes"] <= args.reference_max_nodes:
            try:
                entry["reference"] = bench_reference(problem, cfg, joint, args)
            except Exception as exc:  # noqa: BLE001
                entry["reference"] = {"error": f"{type(exc).__name__}: {exc}"}
                traceback.print_exc()
            res["memory"].append(memory_snapshot(f"reference {p['nodes']} nodes"))
        del problem, setups
    if args.quickstart:
        try:
            res["quickstart"] = bench_quickstart(args.quickstart_set)
        except Exception as exc:  # noqa: BLE001
            res["quickstart"] = {"error": f"{type(exc).__name__}: {exc}"}
            traceback.print_exc()
        res["memory"].append(memory_snapshot("quickstart"))
    if args.keep_profiles is not None and not args.no_split_profile:
        n = profiling.keep_hlo(HLO_DUMP, args.keep_profiles / "hlo")
        log(f"kept figure 2b's traces and the step's HLO ({n} programs) in {args.keep_profiles}")
    res["total_s"] = time.perf_counter() - t_start

    host = "".join(ch for ch in machine["host"].split(".")[0] if ch.isalnum() or ch == "-")[:16] or "host"
    stem = f"{started.strftime('%Y%m%dT%H%M%SZ')}-{machine['backend']}-{host}" + ("-quick" if args.quick else "")
    md = markdown(res)
    atomic_write(args.out / f"{stem}.json", json.dumps(_jsonable(res), indent=1))
    atomic_write(args.out / f"{stem}.md", md)
    print()
    print(md)
    log(f"wrote {args.out / stem}.json and .md ({res['total_s']:.0f} s)")
    return res


if __name__ == "__main__":
    try:
        main()
    finally:
        profiling.remove(HLO_DUMP)

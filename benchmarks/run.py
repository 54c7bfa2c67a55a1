"""Speed of bayesreg's log-density and of its two samplers, per device.

Run from the repository root (not part of the test suite)::

    python benchmarks/run.py --quick                 # a few minutes: one coarse mesh, 1 and 3 chains
    python benchmarks/run.py                         # 24 and 16 mm meshes; 1, 3 and 16 chains
    python benchmarks/run.py --chains 1,3,64,256,1024 --meshes 16 --kernels rwmh   # a GPU

For each mesh (``EDGE`` or ``EDGE@RESOLUTION`` in mm: the MNI152 brain meshed at that edge
length on images of that resolution, with a smooth synthetic shift; built once and cached in
``benchmarks/.cache/``), two problems share the mesh: the paper's three-compartment model
(``configs/paper_three_compartment.yaml``) and the quickstart's (``configs/quickstart.yaml``).
Measured:

* **log-density**: one jitted evaluation at a chain's start, the interior CG solve started
  from zeros (cold) and from the solution at a position one paper-kernel proposal away
  (warm), with the CG preconditioner that the sampler uses (the dense ``K_ii^-1`` is built
  at the start; its build time is given too), and the CG iterations; for the quickstart
  model also the gradient that a NUTS leapfrog step takes.  On the paper model, the
  log-density is compared with a NumPy/SciPy implementation (``benchmarks/reference.py``)
  at CG tolerance 1e-13, and that implementation's own random walk is timed (one chain).
* **steps/s per chain** of two kernels at each chain count: ``rwmh``, the paper's joint
  random walk (Eq. 14) on the paper model, from the config's starts with its fixed scales;
  ``nuts``, the default kernel (NUTS on ``u_b`` in Gibbs with the elastic random walk) on
  the quickstart model, from the chains' states after a short warm-up (Stan's windows).
  The chains run as the samplers run them: chunks of :func:`bayesreg.sampling.chains.build_chunk`
  (the paper configs' 1,000 random-walk steps, ``--nuts-chunk`` NUTS transitions; each
  chain's preconditioner rebuilt at every chunk start), mapped by ``--chain-method`` (NUTS:
  never in pieces, as :func:`bayesreg.sampling.kernels.gibbs.as_algorithm`); the first chunk, which
  compiles, is not timed.  More chains than starts repeat the starts with their own keys.

Writes ``<out>/<UTC time>-<backend>[-quick].json`` and ``.md`` (the tables, also printed),
with the machine (CPU, cores, JAX backend and devices, git commit).
"""

from __future__ import annotations

import argparse
import datetime as dt
import hashlib
import json
import math
import os
import platform
import socket
import subprocess
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

import bayesreg
from bayesreg.sampling import chains
from bayesreg.checkpoint import Checkpoint
from bayesreg.config import load_config, override_config
from bayesreg.inference.initialisation import initialise
from bayesreg.sampling.kernels import gibbs, rwmh
from bayesreg.model.posterior import log_density
from bayesreg.model.problem import assemble, at_start, make_data
from bayesreg.sampling.driver import sample
from bayesreg.inference.targets import (
    cg_preconditioner, dense_preconditioning, gradient_target, make_logdensity, rw_preconditioner)

REPO = Path(__file__).resolve().parent.parent
PAPER_CONFIG = REPO / "configs" / "paper_three_compartment.yaml"
DEFAULT_CONFIG = REPO / "configs" / "quickstart.yaml"
PAPER_STEPS_PER_S = 5.0  # per chain (paper Sec. 4)
KERNELS = ("rwmh", "nuts")

#: settings of a full run and of ``--quick``
PROFILES = {
    "full": {"meshes": "24,16", "chains": "1,3,16", "rw_chunk_steps": 1000, "nuts_chunk": 20,
             "nuts_warmup": 100, "timed_chunks": 2, "time_target_s": 2.0, "reference_seconds": 10.0},
    "quick": {"meshes": "26@3", "chains": "1,3", "rw_chunk_steps": 200, "nuts_chunk": 5,
              "nuts_warmup": 30, "timed_chunks": 2, "time_target_s": 0.5, "reference_seconds": 2.0},
}


def log(msg: str) -> None:
    print(f"[{time.strftime('%H:%M:%S')}] {msg}", flush=True)


def block(x):
    return jax.block_until_ready(x)


def time_call(fn, *args, target_s: float, min_reps: int = 5) -> float:
    """Median seconds per call of ``fn(*args)`` after two warm-up calls (the first compiles),
    over calls repeated for ``target_s`` (at least ``min_reps``)."""
    for _ in range(2):
        block(fn(*args))
    times = []
    t_start = time.perf_counter()
    while len(times) < min_reps or time.perf_counter() - t_start < target_s:
        t = time.perf_counter()
        block(fn(*args))
        times.append(time.perf_counter() - t)
    return float(np.median(times))


def git(*args) -> str | None:
    try:
        return subprocess.run(["git", *args], cwd=REPO, capture_output=True, text=True,
                              timeout=10).stdout.strip() or None
    except (OSError, subprocess.SubprocessError):
        return None


def machine_info() -> dict:
    """CPU, cores, memory, JAX backend and devices, git commit."""
    cpu = platform.processor() or "unknown"
    try:
        cpu = next(line.split(":", 1)[1].strip() for line in
                   Path("/proc/cpuinfo").read_text().splitlines() if line.startswith("model name"))
    except (OSError, StopIteration):
        pass
    devices = jax.devices()
    return {
        "host": socket.gethostname(), "cpu": cpu, "cores": chains.available_cores(),
        "load_average": [round(x, 2) for x in os.getloadavg()], "python": platform.python_version(),
        "jax": jax.__version__, "backend": jax.default_backend(),
        "device": f"{len(devices)} x {devices[0].device_kind}", "xla_flags": os.environ.get("XLA_FLAGS", ""),
        "git_commit": git("rev-parse", "--short", "HEAD"),
        "git_dirty": bool(git("status", "--porcelain", "--untracked-files=no")),
    }


# ---------------------------------------------------------------------------------------------
# problems
# ---------------------------------------------------------------------------------------------

def parse_mesh(spec: str) -> tuple[float, float]:
    """``"EDGE"`` or ``"EDGE@RESOLUTION"`` (mm) -> ``(edge, resolution)``; 2 mm images by default."""
    edge, _, res = spec.partition("@")
    return float(edge), float(res) if res else 2.0


def mesh_overrides(edge: float, res: float) -> list[str]:
    """One mesh at the edge length (no re-meshing to a node count), a smooth synthetic shift
    of 7.5 mm (the paper's constrained truth does not scale to fine meshes; a step's cost
    does not depend on the truth)."""
    return [f"mesh.edge_length_mm={edge:g}", "mesh.target_nodes=null", f"data.resolution_mm={res:g}",
            "synthetic.truth=smooth", "synthetic.shift_mm=7.5", "output.progress=false"]


def cached_data(cfg, cache: Path, prefix: str, rebuild: bool = False):
    """The images, mesh and synthetic truth of ``cfg`` (:func:`bayesreg.model.problem.make_data`),
    from ``cache`` or made and cached there: fTetWild is not reproducible, so later runs
    measure the same mesh.  The file is keyed by ``prefix`` and a hash of the config's
    ``data``, ``mesh`` and ``synthetic`` sections.  Returns ``(data, from_cache)``."""
    sections = {k: cfg.model_dump(mode="json")[k] for k in ("data", "mesh", "synthetic")}
    tag = hashlib.sha1(json.dumps(sections, sort_keys=True).encode()).hexdigest()[:8]
    store = Checkpoint(cache / f"{prefix}-{tag}")
    if store.problem_path.is_file() and not rebuild:
        return store.load_problem(), True
    log(f"building the problem ({prefix}): images, meshing, synthetic truth")
    data = make_data(cfg)
    store.save_problem(data)
    return data, False


def problem_data(edge: float, res: float, cache: Path, rebuild: bool = False):
    """:func:`cached_data` of the benchmark's problem at this mesh size (the paper config's
    data, with :func:`mesh_overrides`); both kernels' models are assembled on it."""
    cfg = load_config(PAPER_CONFIG, overrides=mesh_overrides(edge, res))
    return cached_data(cfg, cache, f"mesh-e{edge:g}-r{res:g}", rebuild)


def kernel_config(kernel: str, edge: float, res: float, extra=()):
    """The config of a kernel's problem at this mesh size."""
    path = PAPER_CONFIG if kernel == "rwmh" else DEFAULT_CONFIG
    return load_config(path, overrides=mesh_overrides(edge, res) + list(extra))


def run_problem(run_dir: Path, kernel: str, overrides=()):
    """``(cfg, problem, init)`` of a run's checkpoint (``--run RUN_DIR`` of
    ``profile_step.py`` and ``samplers.py``): its config with ``overrides``, its problem
    (images, mesh, truth) and its chains' starts, for ``kernel``.

    Raises
    ------
    ValueError
        The checkpoint holds no starts, or they were made for the other kernel family (the
        random walk's scales and the gradient kernels' preconditioner do not fit each other).
    """
    ckpt = Checkpoint(run_dir)
    base = ckpt.load_config()
    init = ckpt.load_init()
    if init is None:
        raise ValueError(f"--run {run_dir}: its checkpoint holds no starts")
    if (kernel == "rwmh") != (base.sampler.kind == "rwmh"):
        raise ValueError(f"--run {run_dir} was started for {base.sampler.kind}: its starts and "
                         f"preconditioner do not fit {kernel}")
    cfg = override_config(base, list(overrides)) if overrides else base
    return cfg, at_start(assemble(cfg, ckpt.load_problem()), cfg, init), init


def with_chains(cfg, n: int):
    """``cfg`` with ``sampler.chains`` set to ``n`` (at least 2, the config's minimum: the
    dense preconditioner's budget, the one thing it decides here, is the same for one)."""
    return override_config(cfg, [f"sampler.chains={max(2, n)}"])


# ---------------------------------------------------------------------------------------------
# log-density
# ---------------------------------------------------------------------------------------------

def bench_logdensity(problem, cfg, x0, sigma, n_chains: int, args) -> dict:
    """Cold and warm evaluations at ``x0``, with the sampler's CG preconditioner for
    ``n_chains`` chains (dense ``K_ii^-1`` built at ``x0``, else the posterior's own)."""
    post = problem.posterior
    zeros = jnp.zeros((post.op.n_interior, 3))
    x = jnp.asarray(x0)
    x2 = x + jnp.asarray(sigma * np.random.default_rng(1).standard_normal(x.shape))
    name = cg_preconditioner(problem, cfg, n_chains=n_chains)
    out = {"preconditioner": name}
    if name == "dense":
        build = jax.jit(rw_preconditioner(problem, cfg).build)
        out["preconditioner_build_ms"] = 1e3 * time_call(build, x, target_s=args.time_target_s)
        pre = block(build(x))
        fn = jax.jit(make_logdensity(problem, cfg, preconditioned=True))
        f = lambda theta, guess: fn(theta, guess, pre)  # noqa: E731
    else:
        f = jax.jit(make_logdensity(problem, cfg))
    guess = block(f(x2, zeros))[1].interior
    for label, theta, start in (("cold", x, zeros), ("warm", x, guess)):
        out[f"{label}_ms"] = 1e3 * time_call(f, theta, start, target_s=args.time_target_s)
        lp, aux = f(theta, start)
        out[f"{label}_cg"] = int(aux.solve.iterations)
        out["finite"] = bool(np.isfinite(float(lp)))
    return out


def bench_gradient(target, state, cache, args) -> float:
    """Milliseconds of the value and gradient of the NUTS target's ``u_b`` log-density
    (one leapfrog step's evaluation)."""
    vg = jax.jit(jax.value_and_grad(target.u_logdensity))
    return 1e3 * time_call(vg, state.u.position, state.eta, cache, state.interior,
                           target_s=args.time_target_s)


def bench_reference(problem, cfg, x0, sigma, args) -> dict:
    """The log-density against the NumPy/SciPy reference, and the reference's random walk."""
    from reference import ReferencePosterior, reference_mh  # benchmarks/reference.py

    ref = ReferencePosterior(problem, cfg)
    post = problem.posterior
    zeros = jnp.zeros((post.op.n_interior, 3))
    tight = jax.jit(lambda th: log_density(post, th, zeros, rtol=1e-13, maxiter=50 * cfg.solver.maxiter)[0])
    rng = np.random.default_rng(5)
    diffs = []
    for theta in (x0, x0 + sigma * rng.standard_normal(x0.shape)):
        r, j = ref(theta), float(tight(jnp.asarray(theta)))
        diffs.append(abs(j - r) / abs(r) if np.isfinite(r) and np.isfinite(j) else float("inf"))
    mh = reference_mh(ref, x0, sigma, 10**6, max_seconds=args.reference_seconds)
    return {"max_rel_diff": max(diffs), "steps_per_s": mh["steps_per_s"], "acceptance": mh["acceptance"]}


# ---------------------------------------------------------------------------------------------
# chains
# ---------------------------------------------------------------------------------------------

def run_chunks(kernel, states, params, n_chains: int, n_draws: int, thin: int, timed: int,
               method: str, profiler=None) -> dict:
    """One compiling chunk and ``timed`` timed chunks of ``n_draws`` draws (``thin`` steps
    each) of every chain; steps/s per chain over the timed chunks, and their statistics.

    With a ``profiler`` (``profiling.ChunkProfiler``, ``benchmarks/profile_step.py``) one
    more chunk runs under it after the timed ones (its figures are not in the others)."""
    mapped = chains.build_chunk(kernel, n_draws, thin, n_chains, method=method)
    key = jax.random.key(4)
    outs, stamps = [], [time.perf_counter()]
    for k in range(1 + timed + (profiler is not None)):
        if k == 1 + timed:
            profiler.start(expected_s=(stamps[-1] - stamps[1]) / timed)
        states, out = mapped.run(jax.random.split(jax.random.fold_in(key, k), n_chains), states, params)
        out = tuple(np.asarray(o) for o in block(out))
        stamps.append(time.perf_counter())
        if k == 1 + timed:
            profiler.stop()
        elif k:
            outs.append(out)
    seconds = stamps[1 + timed] - stamps[1]
    steps = timed * n_draws * thin
    acc = np.concatenate([o[3] for o in outs], axis=1)
    row = {
        "chains": n_chains, "chain_method": mapped.method, "steps_per_s_per_chain": steps / seconds,
        "steps_per_s_total": n_chains * steps / seconds, "timed_steps_per_chain": steps,
        "timed_s": seconds, "first_chunk_incl_compile_s": stamps[1] - stamps[0],
        "acceptance": acc.reshape(-1, acc.shape[-1]).mean(axis=0).tolist(),
        "cg_per_step": float(np.mean([o[4].mean() for o in outs])),
        "grads_per_step": float(np.mean([o[6].mean() for o in outs])),
        "solve_failures": int(sum(o[5].sum() for o in outs)),
        "divergences": int(sum(o[7].sum() for o in outs)),
    }
    if profiler is not None:
        row["profiled_chunk_s"] = stamps[-1] - stamps[-2]
    return row


def tile(tree, n: int):
    """The first axis of every leaf repeated cyclically to length ``n``."""
    return jax.tree.map(lambda a: jnp.asarray(a)[np.arange(n) % a.shape[0]], tree)


def rwmh_setup(problem, cfg, init, args):
    """The paper's joint random walk from the config's starts with its fixed scales.

    Returns ``at(c) -> (row, run_chunks arguments)`` for ``c`` chains (more chains than
    starts repeat them), with the CG preconditioner that ``sample`` picks for ``c`` chains."""
    logdensity = make_logdensity(problem, cfg)
    interior0 = jnp.zeros((problem.posterior.op.n_interior, 3))
    starts = jax.jit(jax.vmap(lambda x: rwmh.init(x, logdensity, interior0)))(jnp.asarray(init.x0))
    sigma = tuple(jnp.asarray(s) for s in init.sigma)
    thin = cfg.sampler.thinning

    def at(c):
        dense = dense_preconditioning(problem, cfg, n_chains=c)
        kernel = rwmh.build_kernel(logdensity, preconditioner=rw_preconditioner(problem, cfg) if dense else None)
        row = {"kernel": "rwmh", "chains": c, "preconditioner": cg_preconditioner(problem, cfg, n_chains=c),
               "solves_per_step": 1.0}
        draws = max(1, args.rw_chunk_steps // thin)
        return row, (kernel, tile(starts, c), sigma, c, draws, thin, args.timed_chunks, args.chain_method)

    return at


def nuts_setup(problem, cfg, init, args):
    """The default NUTS-in-Gibbs kernel, from the chains' states after a short warm-up
    (:func:`bayesreg.sampling.driver.sample` of :func:`bayesreg.sampling.kernels.gibbs.as_algorithm`,
    Stan's windows), at its tuned parameters.

    Returns ``(at, warm)``: ``at(c) -> (row, run_chunks arguments)`` for ``c`` chains, and the
    warm-up's figures with the time of one gradient of the target (a leapfrog step's)."""
    s = cfg.sampler
    interior0 = jnp.zeros((problem.posterior.op.n_interior, 3))
    target = gradient_target(problem, cfg, init.center, init.sigma[0])
    t = time.perf_counter()
    algorithm = gibbs.as_algorithm(
        target, interior0, kind=s.kind, step_size=s.step_size,
        eta_scale=init.sigma[1] if target.n_free else np.zeros(0),  # (joint: none)
        dense_mass=s.dense_mass, adapt_mass=s.adapt_mass, elastic_moves=s.elastic_moves,
        max_tree_depth=s.max_tree_depth)
    tuned = sample(jax.random.key(cfg.seed), algorithm, init.x0, thinning=1,
                   warmup_steps=args.nuts_warmup, max_draws=args.nuts_chunk,
                   min_draws=args.nuts_chunk, chunk_draws=args.nuts_chunk, progress=False)
    warm = {"warmup_transitions": tuned.info.warmup_steps, "warmup_s": time.perf_counter() - t,
            "step_size": np.asarray(tuned.sigma[0]).tolist()}
    log(f"  nuts warm-up: {warm['warmup_transitions']} transitions per chain in {warm['warmup_s']:.0f} s, "
        f"step sizes {np.round(tuned.sigma[0], 3).tolist()}")
    states, params = tuned.final_states, gibbs.GibbsParams(*(jnp.asarray(a) for a in tuned.sigma))

    def kernel_of(tg):
        return gibbs.build_kernel(tg, s.kind, num_integration_steps=s.hmc_steps,
                                  jitter_integration_steps=s.hmc_jitter,
                                  max_num_doublings=s.max_tree_depth, elastic_moves=s.elastic_moves)

    one = jax.tree.map(lambda a: jnp.asarray(a)[0], states)
    warm["gradient_ms"] = bench_gradient(target, one, jax.jit(kernel_of(target).init_cache)(one), args)

    def at(c):
        t_c = gradient_target(problem, with_chains(cfg, c), init.center, init.sigma[0])
        method = args.chain_method
        if method in ("auto", "pieces"):  # a NUTS chunk is not cut into pieces (as gibbs.as_algorithm)
            method = chains.resolve_method("auto", c)
        row = {"kernel": "nuts", "chains": c, "preconditioner": t_c.preconditioner,
               "solves_per_step": float(s.elastic_moves + 1) if t_c.condensed and t_c.n_free else None}
        return row, (kernel_of(t_c), tile(states, c), tile(params, c), c, args.nuts_chunk, 1,
                     args.timed_chunks, method)

    return at, warm


def bench_chains(at, counts) -> list[dict]:
    """:func:`run_chunks` at each chain count; a failure (e.g. device memory) is recorded."""
    rows = []
    for c in counts:
        row, run_args = at(c)
        try:
            row.update(run_chunks(*run_args))
        except Exception as exc:  # noqa: BLE001 - keep the other rows
            row["error"] = f"{type(exc).__name__}: {exc}"
        rows.append(row)
        report(row)
    return rows


def report(row: dict) -> None:
    if "error" in row:
        log(f"  {row['kernel']} C={row.get('chains')}: {row['error']}")
        return
    log(f"  {row['kernel']} C={row['chains']} ({row['chain_method']}, {row['preconditioner']}): "
        f"{row['steps_per_s_per_chain']:.3g} steps/s per chain, {row['steps_per_s_total']:.3g} in total, "
        f"acceptance {np.round(row['acceptance'], 2).tolist()}, CG {row['cg_per_step']:.1f} per step "
        f"(first chunk {row['first_chunk_incl_compile_s']:.0f} s)")


# ---------------------------------------------------------------------------------------------
# report
# ---------------------------------------------------------------------------------------------

def _f(x, fmt="{:.3g}"):
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return "-"
    return fmt.format(x)


def _rate(x: float) -> str:
    return f"{x:,.0f}" if x >= 100 else f"{x:.3g}"


def markdown(res: dict) -> str:
    m = res["machine"]
    commit = (m["git_commit"] or "unknown") + (" (uncommitted changes)" if m["git_dirty"] else "")
    lines = [f"# bayesreg benchmark ({res['profile']})", "",
             f"{res['started_utc']}; {m['device']} ({m['backend']}); CPU {m['cpu']}, {m['cores']} cores, "
             f"load {m['load_average'][0]}; JAX {m['jax']}; commit {commit}; {res['total_s']:.0f} s.", "",
             "## Log-density (one evaluation, ms)", "",
             "| mesh | model | nodes | boundary | interior DOFs | preconditioner (build ms) | cold ms (CG) | "
             "warm ms (CG) | NUTS gradient ms | vs SciPy (rel. diff) | SciPy steps/s |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in res["meshes"]:
        for model, ld in r["logdensity"].items():
            pre = ld["preconditioner"] + (f" ({ld['preconditioner_build_ms']:.3g})"
                                          if "preconditioner_build_ms" in ld else "")
            ref = ld.get("reference") or {}
            lines.append(
                f"| {r['mesh']} | {model} | {r['nodes']} | {r['boundary_nodes']} | {r['interior_dofs']} | {pre} | "
                f"{ld['cold_ms']:.3g} ({ld['cold_cg']}) | {ld['warm_ms']:.3g} ({ld['warm_cg']}) | "
                f"{_f(ld.get('gradient_ms'))} | {_f(ref.get('max_rel_diff'), '{:.1e}')} | "
                f"{_f(ref.get('steps_per_s'), '{:.1f}')} |")
    lines += ["", "## Sampler steps per second (compilation excluded)", "",
              "| mesh | kernel | chains | steps/s per chain | total | x paper | acceptance | CG per solve | "
              "gradients per step | preconditioner | chain method |",
              "|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in res["meshes"]:
        for x in r["sampler"]:
            if "error" in x:
                lines.append(f"| {r['mesh']} | {x['kernel']} | {x['chains']} | {x['error']} |||||||")
                continue
            per_solve = x["cg_per_step"] / x["solves_per_step"] if x["solves_per_step"] else None
            paper = x["steps_per_s_per_chain"] / PAPER_STEPS_PER_S if x["kernel"] == "rwmh" else None
            lines.append(
                f"| {r['mesh']} | {x['kernel']} | {x['chains']} | {_rate(x['steps_per_s_per_chain'])} | "
                f"{_rate(x['steps_per_s_total'])} | {_f(paper, '{:.0f}')} | "
                f"{' / '.join(f'{a:.2f}' for a in x['acceptance'])} | {_f(per_solve, '{:.1f}')} | "
                f"{_f(x['grads_per_step'] if x['kernel'] != 'rwmh' else None, '{:.0f}')} | "
                f"{x['preconditioner']} | {x['chain_method']} |")
    return "\n".join(lines) + "\n"


# ---------------------------------------------------------------------------------------------
# main
# ---------------------------------------------------------------------------------------------

def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--quick", action="store_true",
                   help="a coarse mesh on 3 mm images (26@3), 1 and 3 chains, short chunks")
    p.add_argument("--meshes", help="comma-separated EDGE[@RESOLUTION] in mm (default 24,16; quick 26@3)")
    p.add_argument("--chains", help="comma-separated chain counts (default 1,3,16; quick 1,3)")
    p.add_argument("--kernels", default="rwmh,nuts", help="comma-separated, of rwmh, nuts")
    p.add_argument("--chain-method", default="auto", choices=chains.CHAIN_METHODS,
                   help="how the chains run (bayesreg.sampling.chains; nuts never uses pieces)")
    p.add_argument("--out", type=Path, default=REPO / "benchmarks" / "results",
                   help="folder of the JSON and Markdown results (default benchmarks/results)")
    p.add_argument("--cache", type=Path, default=REPO / "benchmarks" / ".cache",
                   help="folder of the cached meshes and images")
    p.add_argument("--rebuild", action="store_true", help="re-mesh even where a cached problem exists")
    p.add_argument("--no-reference", action="store_true", help="skip the NumPy/SciPy reference")
    p.add_argument("--rw-chunk-steps", type=int, help="random-walk steps per chunk (default 1000 "
                   "as the paper configs; quick 200)")
    p.add_argument("--nuts-chunk", type=int, help="NUTS transitions per chunk (default 20; quick 5)")
    p.add_argument("--nuts-warmup", type=int, help="NUTS warm-up transitions per chain before the "
                   "timed chunks (default 100; quick 30)")
    p.add_argument("--timed-chunks", type=int, help="chunks timed after the compiling one (default 2)")
    p.add_argument("--time-target-s", type=float, help="seconds spent timing each log-density figure")
    p.add_argument("--reference-seconds", type=float, help="duration of the reference's random walk")
    args = p.parse_args(argv)
    for k, v in PROFILES["quick" if args.quick else "full"].items():
        if getattr(args, k, None) is None:
            setattr(args, k, v)
    args.mesh_specs = [parse_mesh(s) for s in args.meshes.split(",") if s.strip()]
    args.chain_counts = sorted({int(c) for c in args.chains.split(",") if c.strip()})
    args.kernel_names = [k for k in args.kernels.split(",") if k]
    if set(args.kernel_names) - set(KERNELS):
        p.error(f"unknown kernels {sorted(set(args.kernel_names) - set(KERNELS))}; choose from {KERNELS}")
    return args


def main(argv=None) -> dict:
    args = parse_args(argv)
    bayesreg.configure_jax()  # float64, XLA flags, BLAS threads: before any JAX computation
    sys.path.insert(0, str(Path(__file__).resolve().parent))  # benchmarks/reference.py
    started = dt.datetime.now(dt.timezone.utc)
    t_start = time.perf_counter()
    machine = machine_info()
    log(f"{machine['device']} ({machine['backend']}), CPU {machine['cpu']}, {machine['cores']} cores, "
        f"JAX {machine['jax']}")
    res = {"profile": "quick" if args.quick else "full", "command": [Path(sys.argv[0]).name, *sys.argv[1:]],
           "started_utc": started.isoformat(timespec="seconds"), "machine": machine,
           "settings": {k: getattr(args, k) for k in ("chain_counts", "kernel_names", "chain_method",
                                                        "rw_chunk_steps", "nuts_chunk", "nuts_warmup",
                                                        "timed_chunks")},
           "meshes": []}
    n_starts = max(2, min(max(args.chain_counts), 16))  # starts made; more chains repeat them
    for edge, resolution in args.mesh_specs:
        data, cached = problem_data(edge, resolution, args.cache, args.rebuild)
        mesh = data.mesh
        entry = {"mesh": f"{edge:g} mm" + (f" @ {resolution:g}" if resolution != 2.0 else ""),
                 "nodes": len(mesh.nodes), "tets": len(mesh.tets), "boundary_nodes": len(mesh.boundary),
                 "from_cache": cached, "logdensity": {}, "sampler": []}
        res["meshes"].append(entry)
        log(f"mesh {entry['mesh']}: {entry['nodes']} nodes, {entry['tets']} tets, "
            f"{entry['boundary_nodes']} boundary nodes{' (cached)' if cached else ''}")
        for kernel in args.kernel_names:
            cfg = with_chains(kernel_config(kernel, edge, resolution), n_starts)
            problem = assemble(cfg, data)
            entry["interior_dofs"] = 3 * problem.posterior.op.n_interior
            t = time.perf_counter()
            init = initialise(problem, cfg)
            log(f"  {kernel}: {n_starts} starts in {time.perf_counter() - t:.1f} s")
            model = "paper" if kernel == "rwmh" else "quickstart"
            # one paper-kernel proposal away: the sampler's warm start
            sigma = np.asarray(init.sigma[0]) if kernel == "rwmh" else np.concatenate(
                [np.full(3 * problem.posterior.n_boundary, 0.008), np.full(problem.posterior.n_free, 0.01)])
            ld = bench_logdensity(problem, cfg, init.x0[0], sigma, min(args.chain_counts), args)
            if kernel == "rwmh" and not args.no_reference:
                ld["reference"] = bench_reference(problem, cfg, np.asarray(init.x0[0]), sigma, args)
            entry["logdensity"][model] = ld
            log(f"  log-density ({model}): cold {ld['cold_ms']:.3g} ms ({ld['cold_cg']} CG), warm "
                f"{ld['warm_ms']:.3g} ms ({ld['warm_cg']} CG), {ld['preconditioner']}"
                + (f"; SciPy: rel. diff {ld['reference']['max_rel_diff']:.1e}, "
                   f"{ld['reference']['steps_per_s']:.1f} steps/s" if "reference" in ld else ""))
            if kernel == "rwmh":
                at = rwmh_setup(problem, cfg, init, args)
            else:
                at, entry["nuts_warmup"] = nuts_setup(problem, cfg, init, args)
                ld["gradient_ms"] = entry["nuts_warmup"]["gradient_ms"]
            entry["sampler"] += bench_chains(at, args.chain_counts)
    res["total_s"] = time.perf_counter() - t_start
    stem = f"{started.strftime('%Y%m%dT%H%M%SZ')}-{machine['backend']}" + ("-quick" if args.quick else "")
    md = markdown(res)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / f"{stem}.json").write_text(json.dumps(res, indent=1, default=float))
    (args.out / f"{stem}.md").write_text(md)
    print()
    print(md)
    log(f"wrote {args.out / stem}.json and .md ({res['total_s']:.0f} s)")
    return res


if __name__ == "__main__":
    main()

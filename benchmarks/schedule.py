"""How a CPU runs chains that do not split evenly over its cores: pieces or whole chains.

Run from the repository root (not part of the test suite)::

    python benchmarks/schedule.py                          # paper-joint, 3 chains, 9 rounds
    python benchmarks/schedule.py --kernel blocked-laplace --chunk-draws 20 --rounds 7
    python benchmarks/schedule.py --kernel nuts --chunk-draws 20 --rounds 3

On the paper-size problem of ``benchmarks/run.py`` (``--mesh``, from its cache), one chunk
function of :func:`bayesreg.sampler._build_chunk` is built per schedule and the schedules
are timed in turn, round after round, each continuing its own chains from the same starts
with the same keys (so every schedule does the same arithmetic):

* ``default``: :func:`bayesreg.sampler._chain_pieces` where the chains do not split evenly
  over the cores: one worker per core runs pieces of single chains, each chain's pieces
  in order (3 chains on 2 cores, chunks of a multiple of 4 draws: 4 pieces per chain);
* ``pieces2``: the same with 2 pieces per chain (coarser, fewer dispatches);
* ``threads``: whole chains, one host thread each (:func:`bayesreg.sampler._chain_threads`;
  the only schedule before the pieces).

``--kernel nuts`` measures the gradient kernels' case instead, which keeps the threads: the
quickstart problem (``benchmarks/samplers.py``'s cache, the paper's normaliser) is sampled
whole by :func:`bayesreg.pipeline.sample_problem` (``--warmup`` transitions, then
``--draws`` draws in chunks of ``--chunk-draws``), alternately with the sampling chunks
cut into pieces (forced) and in threads (the default), ``--rounds`` times each; the rate
is sampling draws per second per chain.

With the random walks the first round compiles and is not counted.  A shared 2-core
machine is noisy from one round to the next (single runs of ``run.py`` gave 85-140 steps/s
per chain for one setting), so the figure to read is the median over rounds of each
schedule's rate divided by the ``threads`` rate of the same round.  Writes
``<out>/schedule-<kernel>-<C>.json`` and ``.md``.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
import types
from pathlib import Path

from bayesreg import _xla

_xla.configure()
import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import bayesreg.sampler as smp  # noqa: E402
from bayesreg import pipeline  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
import run as bench  # noqa: E402

REPO = Path(__file__).resolve().parents[1]


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--kernel", default="paper-joint", choices=sorted(bench.KERNELS) + ["nuts"])
    p.add_argument("--warmup", type=int, default=60, help="nuts: warm-up transitions per run")
    p.add_argument("--draws", type=int, default=80, help="nuts: draws per chain per run")
    p.add_argument("--chains", type=int, default=3)
    p.add_argument("--chunk-draws", type=int, default=40, help="draws per chunk (thinning 10)")
    p.add_argument("--rounds", type=int, default=9, help="rounds, the first (compiling) not counted")
    p.add_argument("--mesh", default="16", help="EDGE[@RESOLUTION] mm, as run.py --meshes")
    p.add_argument("--cache", type=Path, default=REPO / "benchmarks" / ".cache")
    p.add_argument("--out", type=Path, default=REPO / "benchmarks" / "results")
    return p.parse_args(argv)


def nuts_rates(args) -> tuple[dict, dict]:
    """``--kernel nuts``: whole quickstart runs, pieces (forced) and threads in turn."""
    import samplers

    cfg = samplers.load_config(samplers.CONFIG, overrides=[
        "model.prior_normaliser=paper", f"sampler.warmup_steps={args.warmup}",
        f"sampler.max_draws={args.draws}", f"sampler.min_draws={args.draws}",
        f"sampler.chunk_draws={args.chunk_draws}", f"sampler.chains={args.chains}",
        "output.progress=false"])
    problem, _ = samplers.problem_for(cfg, args.cache)
    init = pipeline.initialise(problem, cfg)
    default = smp._build_chunk

    def forced(*a, pieces=True, **k):
        return default(*a, pieces=True, **k)

    rates, last = {"pieces": [], "threads": []}, {}
    for r in range(args.rounds):
        for name in rates:
            smp._build_chunk = forced if name == "pieces" else default
            try:
                result, _ = pipeline.sample_problem(problem, cfg, init)
            finally:
                smp._build_chunk = default
            rates[name].append(args.draws / result.timings["sampling_s"])
            last[name] = np.asarray(result.positions)
            bench.log(f"round {r} {name}: {rates[name][-1]:.2f} transitions/s per chain")
    info = {"nodes": len(problem.mesh.nodes), "same_draws": bool(np.allclose(last["pieces"], last["threads"]))}
    return rates, info


def main(argv=None) -> dict:
    args = parse_args(argv)
    if args.kernel == "nuts":
        rates, info = nuts_rates(args)
        return report(args, rates, info, unit="transitions/s", steps=f"{args.draws} draws")
    edge, res = bench.parse_mesh(args.mesh)
    opts = types.SimpleNamespace(truth="smooth", shift_mm=7.5, cache=args.cache, rebuild=False,
                                 laplace_max_gb=6.0)
    problem, _, info = bench.build_problem(edge, res, opts)
    setup = bench.kernel_setup(problem, bench.mesh_overrides(edge, res, opts), args.kernel, args.chains, opts)
    logdensity = pipeline.make_logdensity(problem, setup["cfg"])
    kernel = smp.build_kernel(logdensity, setup["blocks"], setup["condensation"])
    c = args.chains
    x0 = jnp.asarray(setup["x0"][np.arange(c) % len(setup["x0"])])
    zeros = jnp.zeros((problem.posterior.op.n_interior, 3))
    states = jax.jit(jax.vmap(lambda x: smp.init(x, logdensity, zeros)))(x0)
    sigma = tuple(jnp.asarray(s) for s in setup["sigma"])

    default = smp._chain_pieces
    chunks = {}
    for name, pieces in (("default", None), ("pieces2", 2), ("threads", 1)):
        smp._chain_pieces = default if pieces is None else (lambda *a, _p=pieces, **k: _p)
        try:
            chunks[name] = smp._build_chunk(kernel, args.chunk_draws, bench.THINNING, c)
        finally:
            smp._chain_pieces = default
    steps = args.chunk_draws * bench.THINNING
    rates = {k: [] for k in chunks}
    current = dict.fromkeys(chunks, states)
    for r in range(args.rounds):
        keys = jax.random.split(jax.random.key(r), c)
        for name, chunk in chunks.items():
            t = time.perf_counter()
            current[name], _ = chunk(keys, current[name], sigma)
            jax.block_until_ready(current[name])
            rate = steps / (time.perf_counter() - t)
            if r:
                rates[name].append(rate)
            bench.log(f"round {r} {name}: {rate:.1f} steps/s per chain")
    return report(args, rates, info, unit="steps/s", steps=f"{args.chunk_draws} draws x {bench.THINNING}")


def report(args, rates: dict, info: dict, *, unit: str, steps: str) -> dict:
    """Ratios to ``threads`` per round, JSON and Markdown."""
    c = args.chains
    ratios = {k: (np.asarray(v) / np.asarray(rates["threads"])).tolist() for k, v in rates.items()
              if k != "threads"}
    result = {
        "machine": bench.machine_info(), "problem": info, "kernel": args.kernel, "chains": c,
        "chunk_draws": args.chunk_draws, "rounds_timed": len(rates["threads"]),
        "default_pieces": smp._chain_pieces(c, args.chunk_draws), "default_threads": smp._chain_threads(c),
        "rate_unit": f"{unit} per chain", "rates_per_chain": rates, "ratio_to_threads": ratios,
    }
    lines = [f"# CPU schedule of {c} chains ({args.kernel}, {info['nodes']} nodes, "
             f"{steps} per chunk)", "",
             f"{result['machine']['cpu_model']}, {result['machine']['cores_available']} cores, "
             f"commit {result['machine']['git_commit']}", "",
             f"| schedule | {unit} per chain, median (min-max) | / threads, median of rounds (min-max) |",
             "|---|---|---|"]
    for name, v in rates.items():
        r_ = ratios.get(name)
        ratio = "1" if r_ is None else f"{np.median(r_):.2f} ({min(r_):.2f}-{max(r_):.2f})"
        lines.append(f"| {name} | {np.median(v):.1f} ({min(v):.1f}-{max(v):.1f}) | {ratio} |")
    md = "\n".join(lines) + "\n"
    print(md)
    stem = args.out / f"schedule-{args.kernel}-{c}"
    bench.atomic_write(stem.with_suffix(".json"), json.dumps(bench._jsonable(result), indent=1))
    bench.atomic_write(stem.with_suffix(".md"), md)
    bench.log(f"wrote {stem}.json and .md")
    return result


if __name__ == "__main__":
    main()

"""MH steps per second of the paper's random walk in ``bayesreg.sampler.sample``, before/after.

Run from the repository root of each checkout to compare (not part of the test suite)::

    python benchmarks/steps.py --model three_compartment            # tuned states (below)
    python benchmarks/steps.py --model uniform
    python benchmarks/steps.py --model three_compartment --from-starts

The machine this project runs on changes speed by up to 2x within minutes, which swamps a
20% change in any single run (``run.py`` times 2 chunks of one run).  This script is the
unit of an interleaved comparison: run it alternately from two checkouts (a worktree of
the older commit and this one), several rounds, and read the ratios of adjacent runs::

    git worktree add /tmp/before <commit>
    for r in 1 2 3; do for d in /tmp/before .; do
        (cd $d && python benchmarks/steps.py --model uniform); done; done

Both checkouts sample the same problem from the same states with the same keys, so their
chains are the same (the line prints acceptance and CG iterations to show it):

* the problem: ``configs/paper_<model>.yaml`` on ``run.py``'s cached 16 mm mesh (its
  ``benchmarks/.cache/paper-e16-r2-smooth-*.npz``; built by ``run.py --meshes 16`` if
  missing), with the paper's joint isotropic proposal;
* the states: by default the chains after 5,000 warm-up steps (``STATES_WARMUP``; the paper
  configs' own warm-up until 2026-11-25, when they turned to the paper's fixed kernel), saved once in
  ``benchmarks/.cache/steps-<model>.npz`` by whichever checkout runs first (``--rebuild``
  makes them again): for the three-compartment model the paper's drift has by then taken
  ``lam_CSF``, ``mu_CSF`` and ``mu_WM`` near 0 (most proposals leave the support), for the
  uniform model every proposal is solved; ``--from-starts``: the config's starts and scales
  (untuned, as ``run.py``);
* ``--problem RUN/checkpoint/problem.npz``: a real run's problem instead (the config as it
  is: the paper's constrained truth, where the tuned chains accept about a quarter of
  their proposals and solve nearly all of them);
* ``--set KEY=VALUE`` (repeatable): a config override on top of those, such as
  ``solver.rtol=1e-6`` (the tuned states stay those of the cached file);
  ``sampler.blocked=true`` samples ``u_b`` and the elastic parameters in turn, each with
  its part of the joint scale (and ``sampler.condensed=true``, ``sampler.u_moves=N`` with
  it), one step being one update of each block;
* the timing: 3 chains (``--chains``) x ``--chunks`` chunks of 100 draws (thinning 10, the
  configs' chunk), the first chunk (compilation) excluded, between ``on_chunk`` time stamps.
"""

from __future__ import annotations

import argparse
import contextlib
import glob
import sys
import time
from pathlib import Path

from bayesreg import _xla

_xla.configure()
import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

from bayesreg import pipeline  # noqa: E402
from bayesreg.config import load_config  # noqa: E402
from bayesreg.sampler import sample  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
CACHE = REPO / "benchmarks" / ".cache"
STATES_WARMUP = 5000  # warm-up steps per chain of the cached tuned states


def main(argv=None, around_sampling=None) -> dict:
    """Run the comparison; ``around_sampling()``, a context manager, wraps the timed
    ``sample`` call alone (``profile_step.py`` profiles it; the tuned states' warm-up and
    the problem's loading stay outside)."""
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--model", choices=("three_compartment", "uniform"), default="three_compartment")
    p.add_argument("--from-starts", action="store_true", help="the config's starts and scales, untuned")
    p.add_argument("--chunks", type=int, default=3, help="chunks of 100 draws (the first is not timed)")
    p.add_argument("--chains", type=int, default=3, help="chains (>= 2; the cached states' 3 "
                   "repeated or cut)")
    p.add_argument("--rebuild", action="store_true", help="make the tuned states again")
    p.add_argument("--problem", help="a run's checkpoint/problem.npz instead of the cached 16 mm "
                   "problem, sampled with the config unchanged (its own truth and kernel); tuned "
                   "states cached beside the others as steps-<model>-<name of the run>.npz")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="a config override on top of the script's (e.g. solver.rtol=1e-6)")
    args = p.parse_args(argv)
    if args.chunks < 2:
        p.error("--chunks must be >= 2 (the first chunk compiles and is not timed)")
    if args.chains < 2:
        p.error("--chains must be >= 2 (sample() needs two chains for R-hat)")

    if args.problem:
        cfg = load_config(REPO / "configs" / f"paper_{args.model}.yaml", overrides=args.set)
        found = [args.problem]
        tag = f"-{Path(args.problem).resolve().parents[1].name}"
    else:
        cfg = load_config(REPO / "configs" / f"paper_{args.model}.yaml",
                          overrides=["mesh.edge_length_mm=16", "mesh.target_nodes=null", "data.resolution_mm=2", "synthetic.truth=smooth",
                                     "sampler.blocked=false", "sampler.proposal=isotropic", *args.set])
        found = sorted(glob.glob(str(CACHE / "paper-e16-r2-smooth-*.npz")))
        tag = ""
    if not found:
        sys.exit("no cached 16 mm problem: run `python benchmarks/run.py --meshes 16 --chains 3` first")
    problem = pipeline.load_problem(found[0], cfg)
    n_i = problem.posterior.op.n_interior
    logdensity = pipeline.make_logdensity(problem, cfg)
    pre = (pipeline._preconditioner_rw(problem, cfg)
           if pipeline.dense_preconditioning(problem, cfg, n_chains=args.chains) else None)
    states = CACHE / f"steps-{args.model}{tag}.npz"
    if args.from_starts or args.rebuild or not states.is_file():  # the config's starts and scales
        init = pipeline.initialise(problem, cfg)
        x0, sigma, interior0 = np.asarray(init.x0), tuple(np.asarray(s) for s in init.sigma), np.zeros((n_i, 3))
    if not args.from_starts:
        if args.rebuild or not states.is_file():
            if cfg.sampler.blocked:
                sys.exit(f"{states.name} holds the joint kernel's tuned states: make them "
                         "without --set sampler.blocked=true, then sample them with it")
            print(f"warm-up of {STATES_WARMUP} steps per chain for {states.name}", flush=True)
            warm = sample(jax.random.key(1), logdensity, x0, jnp.zeros((n_i, 3)), sigma,
                          thinning=10, warmup_steps=STATES_WARMUP, max_draws=100,
                          min_draws=100, chunk_draws=100, progress=False, preconditioner=pre)
            np.savez(states, position=np.asarray(warm.final_states.position),
                     interior=np.asarray(warm.final_states.interior),
                     **{f"sigma{k}": np.asarray(s) for k, s in enumerate(warm.sigma)})
        z = np.load(states)
        x0, interior0 = z["position"], z["interior"][0]
        sigma = tuple(z[f"sigma{k}"] for k in range(len([f for f in z.files if f.startswith("sigma")])))

    x0 = np.resize(np.asarray(x0), (args.chains, np.shape(x0)[-1]))  # chain c: start c mod 3
    # the kernel's blocks as pipeline.sample_problem makes them: with sampler.blocked, u_b
    # and the elastic parameters in turn (the tuned states' joint scale split between them)
    nb3 = 3 * problem.posterior.n_boundary
    blocks = condensation = None
    if cfg.sampler.blocked:
        blocks = (np.arange(nb3), np.arange(nb3, problem.posterior.dim))
        if len(sigma) == 1:
            if np.ndim(sigma[0]) != 1:
                sys.exit("--set sampler.blocked=true needs the isotropic proposal's scales (a vector)")
            sigma = (sigma[0][:nb3], sigma[0][nb3:])
        if cfg.sampler.use_condensed:
            condensation = pipeline._condensed_rw(problem, cfg)
    stamps: list[float] = []

    def on_chunk(_ckpt, out):
        if out is not None:
            stamps.append(time.perf_counter())

    with around_sampling() if around_sampling is not None else contextlib.nullcontext():
        res = sample(jax.random.key(3), logdensity, x0, jnp.asarray(interior0), sigma, thinning=10,
                     warmup_steps=0, max_draws=100 * args.chunks, min_draws=100 * args.chunks,
                     chunk_draws=100, progress=False, preconditioner=pre, on_chunk=on_chunk,
                     blocks=blocks, condensation=condensation)
    steps = 1000 * (args.chunks - 1)  # per chain
    rate = steps / (stamps[-1] - stamps[0])
    out = {"model": args.model, "states": "starts" if args.from_starts else "tuned",
           "steps_per_s_per_chain": rate, "acceptance": float(res.acceptance[:, 100:].mean()),
           "cg_iterations_per_step": float(res.cg_iterations[:, 100:].mean()),
           # (a checkout older than cg_preconditioner knew only dense and block Jacobi)
           "cg_preconditioner": (pipeline.cg_preconditioner(problem, cfg, n_chains=args.chains)
                                 if hasattr(pipeline, "cg_preconditioner")
                                 else "dense" if pre is not None else "block-jacobi")}
    out["chains"] = args.chains
    out["steps_total_per_chain"] = 1000 * args.chunks  # the compiling chunk's too
    acc = f"acceptance {out['acceptance']:.3f}"
    if blocks is not None:  # per block: u_b, elastic
        out["acceptance_per_block"] = [float(a) for a in res.acceptance[:, 100:].mean(axis=(0, 1))]
        acc = "acceptance u_b / elastic " + " / ".join(f"{a:.3f}" for a in out["acceptance_per_block"])
    print(f"{REPO.name} {args.model} ({out['states']}, {args.chains} chains"
          f"{', blocked: a step updates each block' if blocks is not None else ''}): {rate:.1f} MH steps/s "
          f"per chain ({args.chains * rate:.0f} in total), {acc}, "
          f"CG iterations per step {out['cg_iterations_per_step']:.2f} ({out['cg_preconditioner']})")
    return out


if __name__ == "__main__":
    main()

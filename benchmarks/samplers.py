"""Compare the samplers (RW-MH, MALA, HMC, NUTS) on the quickstart problem by ESS per second.

``benchmarks/run.py`` gives a kernel's cost (steps per second); this script gives what a
step buys.  For each kernel: one run of ``configs/quickstart.yaml`` (its mesh and synthetic
truth built once and cached in ``benchmarks/.cache/``) through
:func:`bayesreg.pipeline.sample_problem`, no early stop, then from the stored draws:

* min bulk ESS over every monitored estimand (boundary coordinates, free parameters, lam/mu
  ratios), per second of sampling and of start-up + warm-up + sampling;
* wall time until the rank-normalised split R-hat (ArviZ) < 1.01 and until the classic
  Gelman-Rubin R-hat < 1.2 on every estimand, from R-hat on every prefix of whole chunks
  (time of a prefix: start-up + warm-up + its share of the sampling time);
* gradient evaluations per step and per stored draw, acceptance, divergences.

Run from the repository root::

    python benchmarks/samplers.py                          # the four kernels, the quickstart's model
    python benchmarks/samplers.py --kinds nuts --set sampler.joint=false --set sampler.elastic_moves=24 --tag gibbs
    python benchmarks/samplers.py --run RUN_DIR --kinds nuts --set model.interpolation=cubic --tag cubic

``--run RUN_DIR`` takes the problem, config and starts from a run's checkpoint (a paper-size
BrainWeb run, say) instead of the quickstart's: every variant then starts from that run's
chains' starts and preconditioner (made for the run's own model), so that two variants
differ in what ``--set`` changes alone.  The run's prior normaliser is kept unless
``--normaliser`` is given.

Writes ``samplers-<normaliser>[-tag].json`` and ``.md`` in ``--out`` (default
``benchmarks/results/``).  Several minutes per kernel on a 2-core CPU.
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import run  # noqa: E402  (benchmarks/run.py: the cached problem)

import bayesreg  # noqa: E402
from bayesreg.config import load_config  # noqa: E402
from bayesreg.sampling.convergence import gelman_rubin  # noqa: E402
from bayesreg.inference.initialisation import initialise  # noqa: E402
from bayesreg.pipeline import sample_problem  # noqa: E402
from bayesreg.model.posterior import elastic_groups  # noqa: E402
from bayesreg.model.problem import assemble  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
CONFIG = REPO / "configs" / "quickstart.yaml"

# per kernel: (thinning, overrides); warm-up and draws are given in steps / draws below
KINDS = {
    "rwmh": (10, ["sampler.kind=rwmh", "sampler.blocked=true", "sampler.proposal=laplace",
                  "sampler.condensed=true"]),
    "mala": (1, ["sampler.kind=mala"]),
    "hmc": (1, ["sampler.kind=hmc", "sampler.hmc_steps=16"]),
    "nuts": (1, ["sampler.kind=nuts"]),
}


def estimands(problem, draws):
    post = problem.posterior
    nb3 = 3 * post.n_boundary
    lam_g, mu_g = (np.asarray(a) for a in elastic_groups(post, draws[..., nb3:]))
    return np.concatenate([draws, lam_g / mu_g], axis=-1)


def _name(j: int, nb3: int, problem) -> str:
    """Estimand ``j``: a boundary coordinate, a free parameter or a ratio."""
    n_free = problem.posterior.n_free
    if j < nb3:
        return f"u_b[{j // 3}].{'xyz'[j % 3]}"
    if j < nb3 + n_free:
        return f"phi[{j - nb3}]"
    return f"lam/mu[{problem.layout.group_names[j - nb3 - n_free]}]"


def rank_rhat_max(x):
    import arviz as az

    return float(np.nanmax(np.asarray(az.rhat(x, method="rank"))))


def measure(kind: str, args) -> dict:
    thin, extra = KINDS[kind]
    draws = args.draws if kind != "rwmh" else args.draws_rw
    warm = args.warmup if kind != "rwmh" else args.warmup_rw
    chunk = max(2, draws // args.prefixes)
    normaliser = args.normaliser or (None if args.run else "paper")
    overrides = extra + ([f"model.prior_normaliser={normaliser}"] if normaliser else []) + [
        f"sampler.thinning={thin}", f"sampler.warmup_steps={warm}", f"sampler.max_draws={draws}",
        f"sampler.min_draws={draws}", f"sampler.chunk_draws={chunk}", "output.progress=false",
        f"seed={args.seed}"] + list(args.set or [])
    if args.run is not None:  # the run's problem and starts, the variant's settings
        try:
            cfg, problem, init = run.run_problem(args.run, kind, overrides)
        except ValueError as exc:
            raise SystemExit(str(exc)) from None
        t_init = 0.0  # (the run's own starts: no mode search here)
    else:
        cfg = load_config(CONFIG, overrides=overrides)
        data, _ = run.cached_data(cfg, args.cache, "quickstart")
        problem = assemble(cfg, data)
        t0 = time.perf_counter()
        init = initialise(problem, cfg)
        t_init = time.perf_counter() - t0
    result, _ = sample_problem(problem, cfg, init)
    tm = result.timings
    t_warm, t_samp = tm.get("warmup_s", 0.0), tm["sampling_s"]
    est = estimands(problem, result.positions)  # (C, D, K)
    n = est.shape[1]
    import arviz as az

    ess = np.asarray(az.ess(est, method="bulk"))
    nb3 = 3 * problem.posterior.n_boundary
    # prefixes of whole chunks
    t_rank, t_classic = None, None
    for m in range(chunk, n + 1, chunk):
        wall = t_init + t_warm + t_samp * m / n
        if t_classic is None and np.nanmax(gelman_rubin(est[:, :m])) < 1.2:
            t_classic = wall
        if t_rank is None and m >= 8 and rank_rhat_max(est[:, :m]) < 1.01:
            t_rank = wall
        if t_rank is not None and t_classic is not None:
            break
    acc = result.acceptance.reshape(-1, result.acceptance.shape[-1]).mean(axis=0)
    steps = n * thin
    return {
        "kind": kind, "chains": int(est.shape[0]), "warmup_steps": warm, "draws_per_chain": n,
        "thinning": thin, "n_estimands": int(est.shape[2]), "init_s": t_init, "warmup_s": t_warm,
        "sampling_s": t_samp, "steps_per_s_per_chain": steps / t_samp,
        "acceptance": acc.tolist(), "divergences": int(result.divergences.sum()),
        "grad_evals_per_step": float(result.grad_evals.mean()),
        "grad_evals_per_draw": float(result.grad_evals.mean() * thin),
        "ess_bulk_min": float(ess.min()), "ess_bulk_median": float(np.median(ess)),
        "ess_bulk_min_elastic": float(ess[nb3:].min()),
        "ess_bulk_lowest": {_name(j, nb3, problem): float(ess[j]) for j in np.argsort(ess)[:6]},
        "ess_bulk_min_per_s_sampling": float(ess.min() / t_samp),
        "ess_bulk_min_per_s_total": float(ess.min() / (t_init + t_warm + t_samp)),
        "rhat_rank_max": rank_rhat_max(est), "rhat_classic_max": float(np.nanmax(gelman_rubin(est))),
        "time_to_rank_rhat_1_01_s": t_rank, "time_to_classic_rhat_1_2_s": t_classic,
        "adapted": {k: np.asarray(v).tolist() for k, v in zip(("a", "b", "c", "d"), result.sigma)}
        if kind != "rwmh" else None,
    }


def markdown(rows, args) -> str:
    import jax

    base = next((r for r in rows if r["kind"] == "rwmh"), None)
    where = f"The problem and starts of `{args.run}`" if args.run else "Quickstart problem"
    normaliser = args.normaliser or ("the run's" if args.run else "paper")
    lines = [f"{where}, elastic parameters sampled, prior normaliser `{normaliser}`, "
             f"{platform.processor() or platform.machine()}, JAX {jax.__version__} ({jax.default_backend()}), "
             f"commit {run.git('rev-parse', '--short', 'HEAD')}.", "",
             "| kernel | steps/s/chain | grads/draw | acceptance u_b, elastic | divergences | min bulk ESS "
             "(elastic) | min-ESS/s sampling | min-ESS/s total | x RW-MH (sampling) | rank R-hat max | "
             "t to rank R-hat<1.01 | t to classic R-hat<1.2 |", "|" + "---|" * 12]

    def f(x, fmt="{:.1f}"):
        return "-" if x is None else fmt.format(x)

    for r in rows:
        ratio = r["ess_bulk_min_per_s_sampling"] / base["ess_bulk_min_per_s_sampling"] if base else None
        lines.append(
            f"| {r['kind']} | {r['steps_per_s_per_chain']:.1f} | {r['grad_evals_per_draw']:.1f} | "
            f"{', '.join(f'{a:.2f}' for a in r['acceptance'])} | {r['divergences']} | "
            f"{r['ess_bulk_min']:.0f} ({r['ess_bulk_min_elastic']:.0f}) | {r['ess_bulk_min_per_s_sampling']:.3f} | "
            f"{r['ess_bulk_min_per_s_total']:.3f} | {f(ratio)} | {r['rhat_rank_max']:.3f} | "
            f"{f(r['time_to_rank_rhat_1_01_s'], '{:.0f} s')} | {f(r['time_to_classic_rhat_1_2_s'], '{:.0f} s')} |")
    return "\n".join(lines) + "\n"


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--kinds", default="rwmh,mala,hmc,nuts")
    p.add_argument("--normaliser", choices=["exact", "paper"], default=None,
                   help="model.prior_normaliser (default: paper on the quickstart, the run's own "
                   "with --run)")
    p.add_argument("--run", type=Path, default=None, metavar="RUN_DIR",
                   help="take the problem, config and starts from a run's checkpoint (e.g. a "
                   "paper-size BrainWeb run) instead of the quickstart's")
    p.add_argument("--draws", type=int, default=400, help="stored draws per chain (gradient kernels)")
    p.add_argument("--warmup", type=int, default=500, help="warm-up steps (gradient kernels)")
    p.add_argument("--draws-rw", type=int, default=1000, help="stored draws per chain (RW-MH, thinning 10)")
    p.add_argument("--warmup-rw", type=int, default=4000)
    p.add_argument("--prefixes", type=int, default=20, help="R-hat checkpoints along the run")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--set", action="append", help="extra config override (repeatable), e.g. "
                   "sampler.adapt_mass=false")
    p.add_argument("--tag", default="", help="suffix of the output file names")
    p.add_argument("--cache", type=Path, default=REPO / "benchmarks" / ".cache")
    p.add_argument("--out", type=Path, default=REPO / "benchmarks" / "results")
    args = p.parse_args(argv)
    bayesreg.configure_jax()  # float64, XLA flags, BLAS threads: before any JAX computation
    rows = []
    args.out.mkdir(parents=True, exist_ok=True)
    for kind in args.kinds.split(","):
        t = time.perf_counter()
        rows.append(measure(kind, args))
        print(f"{kind}: {time.perf_counter() - t:.0f} s  " + json.dumps(
            {k: v for k, v in rows[-1].items() if k != "adapted"}, default=float), flush=True)
        stem = args.out / f"samplers-{args.normaliser or ('run' if args.run else 'paper')}{'-' + args.tag if args.tag else ''}"
        stem.with_suffix(".json").write_text(json.dumps(rows, indent=2, default=float))
        stem.with_suffix(".md").write_text(markdown(rows, args))
    print(markdown(rows, args))


if __name__ == "__main__":
    main()

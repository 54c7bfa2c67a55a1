"""The skull constraint under NUTS: the hard ``-inf`` wall alone against a smooth barrier.

One dataset (the paper's Sec. 4.1 constrained truth, where about a third of the boundary
nodes slide on the skull, three-compartment model, paper normaliser, by default on a
coarser mesh so that it runs in minutes), sampled by NUTS once per barrier width
(``model.skull_barrier_mm``; 0 is the hard constraint alone).  For each: divergences (in
all and per chain), adapted step sizes, gradients per transition, min / median bulk ESS and
min-ESS per second of sampling, R-hat (and how many boundary coordinates exceed 1.2), how far
apart the chains' mean positions of a boundary node are (local modes), the boundary error of
the posterior mean, and the number of stored draws with a node in the skull (must be 0: the
hard constraint stays with every barrier).  ``--set model.quadrature_level=1`` measures the
composite quadrature.
Figures go to ``barrier.json`` / ``barrier.md`` in ``--out``.

Run: ``python benchmarks/barrier.py [--widths 0,0.5,1] [--out runs/barrier] [--set key=value ...]``.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from bayesreg import _xla

_xla.configure()
import arviz as az  # noqa: E402
import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402

from bayesreg import pipeline  # noqa: E402
from bayesreg.config import load_config  # noqa: E402
from bayesreg.diagnostics import gelman_rubin  # noqa: E402
from bayesreg.posterior import _node_forbidden  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
CONFIG = REPO / "configs" / "paper_three_compartment_nuts.yaml"
DEFAULTS = ["mesh.edge_length_mm=24", "mesh.target_nodes=null", "sampler.warmup_steps=300", "sampler.max_draws=400",
            "sampler.min_draws=400", "sampler.chunk_draws=50", "output.progress=false"]


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--widths", default="0,0.5,1.0", help="barrier widths in mm (0: hard wall alone)")
    p.add_argument("--out", type=Path, default=REPO / "runs" / "barrier")
    p.add_argument("--set", action="append", default=[], help="config override (repeatable)")
    args = p.parse_args(argv)
    base = DEFAULTS + args.set
    cfg0 = load_config(CONFIG, overrides=base)
    t = time.perf_counter()
    data = pipeline.make_data(cfg0)  # one mesh and truth for every width
    print(f"data, mesh and truth in {time.perf_counter() - t:.0f} s", flush=True)
    rows = []
    for w in (float(x) for x in args.widths.split(",")):
        cfg = load_config(CONFIG, overrides=base + [f"model.skull_barrier_mm={w}"])
        problem = pipeline.assemble(cfg, data)
        post = problem.posterior
        t0 = time.perf_counter()
        init = pipeline.initialise(problem, cfg)
        result, _ = pipeline.sample_problem(problem, cfg, init)
        nb3 = 3 * post.n_boundary
        pos = result.positions  # (C, D, dim)
        ess = np.asarray(az.ess(pos, method="bulk"))
        # stored draws with a node in the skull (boundary by the draw, interior by its solve)
        u_b = pos[..., :nb3].reshape(-1, post.n_boundary, 3)
        u_i = result.interior.reshape(-1, result.interior.shape[-2], 3)
        full = np.concatenate([u_b, u_i], axis=1)[:, np.asarray(post.perm)]  # node order
        bad = jax.jit(jax.vmap(lambda u: jnp.any(_node_forbidden(post, post.nodes + u))))(jnp.asarray(full))
        err = np.linalg.norm(full.mean(0) - np.asarray(problem.truth.u), axis=1)[np.asarray(problem.mesh.boundary)]
        rhat = np.asarray(gelman_rubin(pos))
        # local modes: how far apart the chains' mean positions of a boundary node are
        cm = pos[..., :nb3].reshape(pos.shape[0], pos.shape[1], -1, 3).mean(1)
        spread = np.linalg.norm(cm.max(0) - cm.min(0), axis=-1)
        rows.append({
            "barrier_mm": w, "quadrature_level": cfg.model.quadrature_level, "wall_s": time.perf_counter() - t0, "sampling_s": result.timings["sampling_s"],
            "divergences": int(result.divergences.sum()), "transitions": int(pos.shape[0] * pos.shape[1]),
            "divergences_per_chain": result.divergences.reshape(pos.shape[0], -1).sum(1).tolist(),
            "grad_evals_per_step": float(result.grad_evals.mean()),
            "step_size_per_chain": np.asarray(result.sigma[0]).tolist(),
            "acceptance": result.acceptance.reshape(-1, result.acceptance.shape[-1]).mean(0).tolist(),
            "ess_bulk_min": float(ess.min()), "ess_bulk_median": float(np.median(ess)),
            "ess_bulk_min_per_s_sampling": float(ess.min() / result.timings["sampling_s"]),
            "rhat_classic_max": float(np.nanmax(rhat)),
            "u_b_rhat_above_1_2": int(np.sum(rhat[:nb3] > 1.2)),
            "chain_mean_spread_mm_q50_q99_max": np.quantile(spread, [0.5, 0.99, 1.0]).tolist(),
            "rhat_rank_max": float(np.nanmax(np.asarray(az.rhat(pos, method="rank")))),
            "draws_in_skull": int(np.sum(np.asarray(bad))),
            "boundary_error_mm_median_q95_max": np.quantile(err, [0.5, 0.95, 1.0]).tolist(),
        })
        print(json.dumps(rows[-1]), flush=True)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "barrier.json").write_text(json.dumps(rows, indent=2))
    lines = ["| barrier w (mm) | quadrature level | divergences / transitions (per chain) | step size per chain | "
             "grads/step | min bulk ESS | median ESS | min-ESS/s | R-hat classic / rank | u_b R-hat > 1.2 | "
             "chain-mean spread q50 / q99 / max (mm) | draws in skull | boundary error median / 95th / max (mm) |",
             "|" + "---|" * 13]
    for r in rows:
        lines.append(
            f"| {r['barrier_mm']:g} | {r['quadrature_level']} | {r['divergences']} / {r['transitions']} "
            f"({', '.join(map(str, r['divergences_per_chain']))}) | "
            f"{', '.join(f'{s:.3g}' for s in r['step_size_per_chain'])} | {r['grad_evals_per_step']:.0f} | "
            f"{r['ess_bulk_min']:.0f} | {r['ess_bulk_median']:.0f} | {r['ess_bulk_min_per_s_sampling']:.3f} | "
            f"{r['rhat_classic_max']:.2f} / {r['rhat_rank_max']:.2f} | {r['u_b_rhat_above_1_2']} | "
            + " / ".join(f"{e:.2f}" for e in r["chain_mean_spread_mm_q50_q99_max"]) + f" | {r['draws_in_skull']} | "
            + " / ".join(f"{e:.2f}" for e in r["boundary_error_mm_median_q95_max"]) + " |")
    (args.out / "barrier.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()

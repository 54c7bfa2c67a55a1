"""The synthetic data's residual at the truth, and what it does to the elastic ratios.

A synthetic ``m`` is ``f`` warped through the true map and sampled on ``f``'s grid
(:func:`bayesreg.mesh.warp.warp_image`, ``f`` read by its cubic B-spline).  The likelihood
reads ``m`` again by its cubic B-spline at the displaced quadrature points, so even at the
truth ``f(x_q) - m(x_q + u(x_q))`` is not zero: the re-interpolation of a sub-voxel
shift (an image with content up to its Nyquist frequency) and, with smoothing
(``data.smoothing_mm``), the smoothing of ``m`` in its own frame where ``f``'s was in
``f``'s (strain).  Noise-free, that residual is structured, and the chains fit it with the
boundary displacements and the parameters.

For a finished run directory of a synthetic case this prints:

* the residual's rms and ``E_s / T_s`` at the truth, for ``data.smoothing_mm`` 0, 1, 2 and
  3 mm, and by the elements' mean ``|u|`` (where the tissue moves most);
* with ``--sample clean``: the run's posterior once more on the same problem with ``f``'s
  quadrature values replaced by ``m`` at the truth's displaced points (the residual
  removed, nothing else changed; :func:`bayesreg.model.similarity.moving_values`), and its
  ratio medians and 90% intervals beside the run's own; with ``--sample noise`` the same
  plus the Gaussian noise that ``exp(-E_s / T_s)`` implies at each point (data drawn from
  the likelihood: an exact simulation, as ``bayesreg calibrate`` draws it).  Ratios that
  hold their truths on ``clean`` and miss on the run say the miss is the data's residual,
  not the model or the sampler.

Usage (from the repository root; ``--sample`` costs one more run of the sampler)::

    bayesreg run configs/quickstart.yaml --out runs/qs
    python benchmarks/residual.py runs/qs [--sample clean|noise] [--seed 1]
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

import bayesreg
from bayesreg.checkpoint import Checkpoint
from bayesreg.config import override_config
from bayesreg.model.posterior import elastic_groups
from bayesreg.model.problem import assemble
from bayesreg.model.similarity import moving_values


def residual_at_truth(problem, u):
    """``(r, w)``: the residual ``f(x_q) - m(x_q + u(x_q))`` ``(M, Q)`` at the nodal
    displacement ``u`` ``(N, 3)`` mm and the quadrature weights ``(M, Q)`` mm^3 (SSD only)."""
    import jax.numpy as jnp

    term = problem.posterior.similarity
    if getattr(term, "f_q", None) is None:
        raise SystemExit("residual.py: the run's similarity is not the SSD (model.similarity: ssd)")
    m_q = moving_values(term, jnp.asarray(u)[problem.posterior.tets])
    return np.asarray(term.f_q - m_q), np.asarray(term.sqrt_w) ** 2


def ratios(problem, positions) -> np.ndarray:
    """``lam / mu`` per group ``(draws, G)`` of the draws ``positions`` ``(..., dim)``."""
    post = problem.posterior
    phi = np.asarray(positions)[..., post.n_displacement:].reshape(-1, post.n_free)
    lam_g, mu_g = (np.asarray(a) for a in elastic_groups(post, phi))
    return lam_g / mu_g


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("run", type=Path, help="a finished run directory of a synthetic case")
    ap.add_argument("--sample", choices=("clean", "noise"), default=None,
                    help="sample the posterior again without the residual (clean) or with "
                         "data drawn from the likelihood (noise)")
    ap.add_argument("--seed", type=int, default=1, help="the noise's seed (--sample noise)")
    args = ap.parse_args(argv)
    bayesreg.configure_jax()

    ckpt = Checkpoint(args.run)
    cfg, data = ckpt.load_config(), ckpt.load_problem()
    if data.truth is None:
        raise SystemExit("residual.py: not a synthetic run (no truth)")
    u = np.asarray(data.truth.u)
    tets = np.asarray(data.mesh.tets)
    u_el = np.linalg.norm(u, axis=1)[tets].mean(axis=1)
    bins = ((0, 1), (1, 3), (3, 6), (6, np.inf))
    print(f"{args.run}: {len(data.mesh.nodes)} nodes; residual f(x_q) - m(x_q + u(x_q)) at the truth")
    print("smoothing_mm | rms | E_s / T_s | rms by the elements' mean |u| " +
          " / ".join(f"{a}-{b:g} mm" for a, b in bins))
    for s in (0.0, 1.0, 2.0, 3.0):
        problem = assemble(override_config(cfg, [f"data.smoothing_mm={s}"]), data)
        r, w = residual_at_truth(problem, u)
        by = [np.sqrt(np.mean(r[(u_el >= a) & (u_el < b)] ** 2)) if np.any((u_el >= a) & (u_el < b))
              else np.nan for a, b in bins]
        print(f"{s:g} | {np.sqrt(np.mean(r ** 2)):.4f} | "
              f"{np.sum(w * r ** 2) * float(problem.posterior.inv_t_s):.1f} | "
              + " / ".join(f"{v:.4f}" for v in by))
    if args.sample is None:
        return 0

    from bayesreg.pipeline import sample_problem
    import jax.numpy as jnp

    run = bayesreg.open_run(args.run)  # the run's own draws and verdict (a finished run)
    cfg = override_config(cfg, ["output.progress=false"])
    problem = assemble(cfg, data)
    post = problem.posterior
    term = post.similarity
    f_q = moving_values(term, jnp.asarray(u)[post.tets])
    if args.sample == "noise":
        sd = np.sqrt(0.5 / float(post.inv_t_s)) / np.asarray(term.sqrt_w)
        f_q = f_q + sd * np.random.default_rng(args.seed).standard_normal(sd.shape)
    problem = problem._replace(posterior=post._replace(similarity=term._replace(f_q=jnp.asarray(f_q))))
    t = time.perf_counter()
    result, _ = sample_problem(problem, cfg)
    again = ratios(problem, result.positions)
    print(f"sampled again ({args.sample}): {result.positions.shape[1]} draws per chain, "
          f"{time.perf_counter() - t:.0f} s")
    own = np.asarray(run.posterior.posterior["ratio"])
    own = own.reshape(-1, own.shape[-1])
    truth = None
    if problem.phi_true is not None:
        lam_t, mu_t = (np.asarray(a) for a in elastic_groups(post, problem.phi_true))
        truth = lam_t / mu_t
    names = problem.layout.group_names
    print("group | truth | the run: median (90%) | " + args.sample + ": median (90%)")
    for g, name in enumerate(names):
        cells = []
        for draws in (own, again):
            lo, med, hi = np.quantile(draws[:, g], [0.05, 0.5, 0.95])
            held = "" if truth is None else (" holds" if lo <= truth[g] <= hi else " misses")
            cells.append(f"{med:.3g} ({lo:.3g}-{hi:.3g}){held}")
        print(f"{name} | {'-' if truth is None else f'{truth[g]:.3g}'} | {cells[0]} | {cells[1]}")
    print(f"the run's {run.info['sampler']['verdict']}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""What the data say about each tissue's lam/mu at the true boundary displacement.

A diagnostic for ``benchmarks/normaliser.py``: on the same dataset (the paper's Sec. 4.1
constrained truth, three-compartment model, by default the 24 mm mesh with the 32-point
quadrature, the extended ``m`` and the 1 mm barrier of the normaliser runs), the boundary
displacements are held at the truth, ``u_b = u_b*``, and one tissue's ratio ``r_g =
lam_g / mu_g`` is varied (``mu_g`` and every other parameter at the truth).  For each value
the interior comes from the FE solve ``u_i = H(lam, mu) u_b*`` and the script records the
terms of the log posterior (paper Eqs. 9-12):

* the image term ``-E_s / T_s`` (Eq. 1 and the Boltzmann likelihood, Eq. 9),
* the elastic prior ``-E_r / T_r`` (Eq. 12) and, under ``prior_normaliser: exact``, the
  normaliser ``(1/2) log pdet S`` (:func:`bayesreg.posterior.log_normaliser`).

"All terms" adds the prior terms to the image term: under ``paper`` at the truth's ``mu``
(``mu_GM`` fixed, as that model has it); under ``exact`` with the common stiffness scale
``s`` of every ``lam``, ``mu`` profiled out (the image term does not depend on it, and the
prior terms ``(n/2) log s - s E_r / T_r + (1/2) log pdet S``, ``n = 3 n_b - 6``, peak at
``s^ = n T_r / (2 E_r)``, about 35x to 170x the truth's scale on these meshes), which is
where the posterior puts it.

Where the image term peaks is what the images alone say about ``r_g`` given the true
boundary: a peak away from the truth is a bias of the likelihood (its quadrature, the
interpolation of the synthetic ``m``), which no prior normaliser removes; a flat profile
means the ratio is not identified by the images (the posterior then follows the prior).
The curvature at the peak gives the conditional standard deviation of ``log r_g`` under the
image term alone.  The same profiles are then taken at ``u_b^`` (``--no-mode`` skips it), the
conditional mode of the boundary displacements given the true parameters (L-BFGS from the
truth, :func:`bayesreg.pipeline.find_mode` with the parameters fixed): where the likelihood
puts the boundary when the elasticity is right.  The profiles are conditional on one
boundary; the posterior also moves ``u_b``, so they explain the sampled intervals, they do
not replace them.

Run: ``python benchmarks/ratio_profile.py [--set key=value ...] [--out benchmarks/results]``
(about 3 minutes for the default 24 mm mesh on a 2-core CPU, most of it the constrained
truth; the dataset is cached in ``benchmarks/.cache/``).  Writes ``ratio-profile[-tag].json``
and ``.md``.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from bayesreg import _xla

_xla.configure()
import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402

from bayesreg import pipeline  # noqa: E402
from bayesreg.pipeline import find_mode  # noqa: E402
from bayesreg.config import load_config  # noqa: E402
from bayesreg.posterior import log_density, log_normaliser  # noqa: E402
from samplers import problem_for  # noqa: E402  (benchmarks/ is on the path of a script run)

REPO = Path(__file__).resolve().parents[1]
CONFIG = REPO / "configs" / "paper_three_compartment.yaml"
# the normaliser benchmark's dataset and model (its q1 rerun), every parameter free
DEFAULTS = ["mesh.edge_length_mm=24", "mesh.target_nodes=null", "model.quadrature_level=1", "model.skull_barrier_mm=1.0",
            "model.prior_normaliser=exact", "model.fixed=null", "model.prior_lam.r2=1.0e6",
            "model.prior_mu.r2=1.0e5", "output.progress=false"]
FACTORS = np.exp(np.linspace(np.log(1 / 3), np.log(3), 41))  # r_g / r_g*, for GM and WM
FACTORS_WIDE = np.exp(np.linspace(np.log(1e-2), np.log(1e3), 41))  # for CSF


def peak(x, y):
    """Grid maximum refined by a parabola through it and its neighbours, and the curvature
    there: ``(x_peak, -d2y/dx2)`` (``nan`` curvature at the grid's edge)."""
    j = int(np.argmax(y))
    if j == 0 or j == len(y) - 1:
        return float(x[j]), float("nan")
    x0, x1, x2 = x[j - 1:j + 2]
    y0, y1, y2 = y[j - 1:j + 2]
    c = np.polyfit([x0, x1, x2], [y0, y1, y2], 2)
    return float(-c[1] / (2 * c[0])), float(-2 * c[0])


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--set", action="append", default=[], help="config override (repeatable)")
    p.add_argument("--out", type=Path, default=REPO / "benchmarks" / "results")
    p.add_argument("--tag", default="")
    p.add_argument("--cache", type=Path, default=REPO / "benchmarks" / ".cache")
    p.add_argument("--no-mode", action="store_true", help="profiles at the truth only")
    p.add_argument("--config", type=Path, default=CONFIG,
                   help="dataset and model (default: the paper's three-compartment experiment)")
    args = p.parse_args(argv)
    cfg = load_config(args.config, overrides=DEFAULTS + args.set)
    t0 = time.perf_counter()
    problem, cached = problem_for(cfg, args.cache, prefix="ratio-profile")
    post, layout = problem.posterior, problem.layout
    if problem.truth is None or problem.phi_true is None:
        raise ValueError("the profile needs a synthetic truth with per-tissue parameters")
    u_b = np.asarray(problem.truth.u)[np.asarray(post.boundary)]
    phi_true = np.asarray(problem.phi_true, np.float64)
    index = {name: j for j, name in enumerate(layout.free_names)}
    for name in ("lam_csf", "lam_gm", "lam_wm"):
        if name not in index:
            raise ValueError(f"{name} must be free (model.fixed=null); free: {layout.free_names}")
    t_build = time.perf_counter() - t0
    exact = cfg.model.prior_normaliser == "exact"
    n_dof = 3 * post.n_boundary - 6  # rank of S

    @jax.jit
    def terms(u_b, phi, u_i0):
        theta = jnp.concatenate([u_b.ravel(), phi])
        logp, aux = log_density(post, theta, u_i0, rtol=cfg.solver.rtol, maxiter=cfg.solver.maxiter)
        ln = log_normaliser(post, phi) if exact else jnp.zeros(())
        return (-aux.e_s * post.inv_t_s, -aux.e_r * post.inv_t_r, ln, logp, aux.interior,
                aux.solve.converged, aux.solve.iterations)

    def profiles(u_b):
        u_b = jnp.asarray(u_b)
        u_i = jnp.zeros((post.op.n_interior, 3))
        rows = {}
        for g in ("csf", "gm", "wm"):
            j_lam, j_mu = index[f"lam_{g}"], index[f"mu_{g}"]
            truth_ratio = phi_true[j_lam] / phi_true[j_mu]
            factors = FACTORS_WIDE if g == "csf" else FACTORS
            out = {"image": [], "elastic": [], "normaliser": [], "logp": [], "converged": [], "cg": []}
            for f in factors:
                phi = phi_true.copy()
                phi[j_lam] = f * truth_ratio * phi_true[j_mu]
                img, el, ln, lp, u_i, ok, its = terms(u_b, jnp.asarray(phi), u_i)
                for k, v in zip(out, (img, el, ln, lp, ok, its)):
                    out[k].append(float(v) if k not in ("converged", "cg") else int(v))
            if not all(out["converged"]):
                raise RuntimeError(f"{g}: {out['converged'].count(0)} solve(s) did not converge")
            x = np.log(factors * truth_ratio)
            image = np.asarray(out["image"])
            elastic = np.asarray(out["elastic"])  # -E_r / T_r at the truth's scale
            if exact:
                # the common stiffness scale s profiled out as the posterior sees it: the
                # prior terms at s are (n/2) log s - s E_r / T_r + ln, maximal at
                # s^ = n T_r / (2 E_r), leaving ln - (n/2) log(E_r / T_r) + const
                cond = image + np.asarray(out["normaliser"]) - 0.5 * n_dof * np.log(-elastic)
            else:
                cond = image + elastic
            x_img, curv = peak(x, image)
            x_cond, curv_c = peak(x, cond)
            sd = float(1 / np.sqrt(curv)) if curv > 0 else float("nan")
            rows[g] = {
                "truth": float(truth_ratio),
                "image_peak": float(np.exp(x_img)),
                "image_sd_log": sd,
                # distance of the truth from the peak in those sd (nan where flat)
                "truth_offset_sd": float((np.log(truth_ratio) - x_img) / sd),
                "image_range": float(image.max() - image.min()),
                "conditional_peak": float(np.exp(x_cond)),
                "conditional_sd_log": float(1 / np.sqrt(curv_c)) if curv_c > 0 else float("nan"),
                "scale_at_truth": float(n_dof / (-2 * np.interp(np.log(truth_ratio), x, elastic))),
                "ratios": (factors * truth_ratio).tolist(), **out,
            }
            print(g, {k: v for k, v in rows[g].items() if not isinstance(v, list)}, flush=True)
        return rows

    at = {"truth": {"profiles": profiles(u_b)}}
    if not args.no_mode:
        t1 = time.perf_counter()
        cfg_mode = cfg.model_copy(update={"init": cfg.init.model_copy(update={"optimize_parameters": False})})
        theta_mode, info = find_mode(problem, cfg_mode, np.concatenate([u_b.ravel(), phi_true]))
        u_mode = theta_mode[:3 * post.n_boundary].reshape(-1, 3)
        dist = np.linalg.norm(u_mode - u_b, axis=1)
        at["mode"] = {"search_s": time.perf_counter() - t1, "search": info,
                      "boundary_distance_mm": {"median": float(np.median(dist)),
                                               "p95": float(np.quantile(dist, 0.95)),
                                               "max": float(dist.max())},
                      "profiles": profiles(u_mode)}
        print("mode", at["mode"]["boundary_distance_mm"], flush=True)
    result = {"config": str(args.config), "overrides": DEFAULTS + args.set,
              "mesh": {"nodes": int(post.nodes.shape[0]), "tets": int(post.tets.shape[0]),
                       "boundary": int(post.n_boundary)},
              "elements_per_tissue": {g: int(np.sum(np.asarray(problem.element_group) == k))
                                      for k, g in enumerate(layout.group_names)},
              "problem_from_cache": cached, "build_s": t_build, "wall_s": time.perf_counter() - t0,
              "normaliser": cfg.model.prior_normaliser, "at": at}
    tag = f"-{args.tag}" if args.tag else ""
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / f"ratio-profile{tag}.json").write_text(json.dumps(result, indent=2))
    lines = [f"# lam/mu profiles at the true boundary displacement ({result['mesh']['nodes']} nodes, "
             f"{result['mesh']['boundary']} boundary; elements CSF / GM / WM "
             f"{' / '.join(str(v) for v in result['elements_per_tissue'].values())})", "",
             f"`{args.config}` {' '.join('--set ' + s for s in args.set) or '(defaults)'}; normaliser "
             f"`{cfg.model.prior_normaliser}`; others at the truth", "",
             "| `u_b` at | tissue | truth | image-term peak | sd of log r (image) | truth - peak (sd) | "
             "image term's range over the grid (nats) | peak of all terms | sd of log r (all) |",
             "|---|---|---|---|---|---|---|---|---|"]
    for where, block in at.items():
        for g, r in block["profiles"].items():
            lines.append(f"| {where} | {g} | {r['truth']:g} | {r['image_peak']:.4g} | "
                         f"{r['image_sd_log']:.3g} | {r['truth_offset_sd']:.2g} | {r['image_range']:.3g} | "
                         f"{r['conditional_peak']:.4g} | {r['conditional_sd_log']:.3g} |")
    if "mode" in at:
        d = at["mode"]["boundary_distance_mm"]
        lines += ["", f"`u_b^` (conditional mode given the true parameters) lies {d['median']:.3g} / "
                  f"{d['p95']:.3g} / {d['max']:.3g} mm (median / 95th / max over boundary nodes) from "
                  f"`u_b*` ({at['mode']['search_s']:.0f} s)."]
    (args.out / f"ratio-profile{tag}.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()

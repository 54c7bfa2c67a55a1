"""Deformations the model did not make: a finished run against its reference and the FE bound.

For each run directory of a synthetic case (best a truth the model did not make,
``synthetic.truth: bump``, ``random`` or ``field``, or ``synthetic.discrepancy_mm``), prints
one row: the brain-voxel MSE (mm^2) and boundary 95th percentile (mm) of the posterior mean,
of its start and of the run's reference registration on the same images (TV-L1 or ANTs SyN,
``output.reference``; the run's ``errors.json``), the 90% coverage where the truth moves
the tissue at least 1 mm, the GM and WM ``lam/mu`` medians and which parameters sit on their
prior's edge; then the **bound of the model's interior**: the smallest brain-voxel MSE any FE
field can reach whose interior solves ``K u = 0`` (boundary values chosen by least squares
against the truth itself) at the run's posterior-median parameters and over a scan of one
common ``lam/mu``, and that of free nodal values (the mesh's own resolution limit,
:func:`bayesreg.outputs.fields.mesh_best_fit`).  The
bound says how much of the error is the model's, not the sampler's.  Last, the ratios the
model itself reads from a displacement (the parameters' conditional mode given every node's
``u``, :func:`parameters_given`): from the truth's, and from the posterior mean's (30 draws).
Far apart, the ratios are set by the posterior's interior, not by the true field.

Usage (from the repository root)::

    bayesreg run configs/quickstart.yaml --out runs/bump \\
        --set synthetic.truth=bump --set synthetic.lam=null --set synthetic.mu=null \\
        --set synthetic.shift_mm=8 --set synthetic.falloff_mm=20 --set init.start=registration
    python benchmarks/mismatch.py runs/bump [more run directories]
"""

from __future__ import annotations

import argparse
import json
import sys
from functools import partial
from pathlib import Path

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

import bayesreg
from bayesreg.checkpoint import Checkpoint
from bayesreg.fem.element import stiffness_matrix
from bayesreg.data.labels import TISSUE_LABELS
from bayesreg.mesh.warp import interpolation_matrix
from bayesreg.outputs.fields import mesh_best_fit, node_slots
from bayesreg.model.problem import assemble, at_start
from bayesreg.outputs.printed import reference_method


def elastic_fit(mesh, w, target, lam_t, mu_t):
    """Least-squares best FE field ``(V, 3)`` on the voxels of ``w`` (``(V, N)``) whose
    interior solves ``K u = 0`` for tissue values ``lam_t``, ``mu_t`` ``(3,)`` (normal
    equations ``P^T W^T W P u_b = P^T W^T t``, ``P`` the map from boundary values to every
    node: ``W^T W`` is sparse, so no ``(3V, 3 n_b)`` matrix is formed)."""
    k = sp.csr_matrix(stiffness_matrix(mesh.nodes, mesh.tets, lam_t[mesh.tissue], mu_t[mesh.tissue]))
    n, b = len(mesh.nodes), np.asarray(mesh.boundary)
    i = np.setdiff1d(np.arange(n), b)
    bd = (3 * b[:, None] + np.arange(3)).ravel()
    idf = (3 * i[:, None] + np.arange(3)).ravel()
    p = np.zeros((3 * n, 3 * len(b)))
    p[bd, np.arange(3 * len(b))] = 1.0
    p[idf] = -spla.splu(sp.csc_matrix(k[idf][:, idf])).solve(k[idf][:, bd].toarray())
    wtw = sp.kron(w.T @ w, sp.identity(3)).tocsr()
    rhs = p.T @ (w.T @ target).ravel()
    u_b = np.linalg.lstsq(p.T @ (wtw @ p), rhs, rcond=None)[0]
    return (w @ (p @ u_b).reshape(-1, 3))


def _fe_interior(post, lp, u_b, phi):
    """The FE interior solve ``H(phi) u_b`` ``(n_i, 3)`` mm (``Aux.interior``: without the
    discrepancy) through ``lp``, a :func:`~bayesreg.inference.targets.logdensity_fn`."""
    import jax.numpy as jnp

    n_d = post.n_displacement - 3 * post.n_boundary
    theta = jnp.concatenate([jnp.ravel(u_b), jnp.zeros(n_d), phi])
    return lp(theta, jnp.zeros((post.op.n_interior, 3)))[1].interior


def parameters_given(problem, us, phi0):
    """The elastic parameters' conditional mode given every node's displacement, for each
    ``u`` ``(N, 3)`` mm of ``us``: ``argmax_phi log p(u_b, d, phi)`` with ``d = u_i - H(phi)
    u_b`` (low rank: its projection on the modes; orthogonal: ``d`` whole in its prior and
    ``P d`` in the images; without a model discrepancy, ``u_b`` alone: the paper's interior
    is the FE solve), the exact normaliser included; the target of the
    collapsed moves that hold ``u``.  L-BFGS-B over ``log phi`` from ``phi0`` ``(n_free,)``,
    the prior's support shrunk by 0.1%, one compiled objective for every ``u``.  Returns the
    groups' ``lam / mu`` ``(len(us), G)`` at the modes, a row of NaN (and a message) where a
    search fails.  Given the truth's ``u`` it says which ratios the model itself reads from
    the true field (apart from the images and the sampler)."""
    import jax
    import jax.numpy as jnp
    import scipy.optimize as so

    from bayesreg.inference.targets import logdensity_fn

    post = problem.posterior
    boundary, interior_nodes = node_slots(problem)
    lp = logdensity_fn(post, exact=True, rtol=1e-10, maxiter=5000)
    low_rank = post.discrepancy is not None and post.discrepancy.basis is not None

    @jax.jit
    @partial(jax.value_and_grad, argnums=0)
    def neg(x, u_b, u_i):
        phi = jnp.exp(x)
        interior = _fe_interior(post, lp, u_b, phi)
        d = (u_i - interior).ravel() if post.discrepancy is not None else jnp.zeros(0)
        if low_rank:  # its coordinates in the modes
            d = d @ post.discrepancy.basis
        return -lp(jnp.concatenate([u_b.ravel(), d, phi]), interior)[0]

    lo, hi = np.maximum(np.asarray(post.prior.r1), 0.0), np.asarray(post.prior.r2)
    bounds = np.log(np.stack([lo + 1e-3 * (hi - lo), hi - 1e-3 * (hi - lo)], axis=1))
    full, g = np.asarray(post.base, float), len(post.base) // 2
    out = np.full((len(us), g), np.nan)
    for k, u in enumerate(us):
        u_b, u_i = jnp.asarray(u[boundary]), jnp.asarray(u[interior_nodes])
        res = so.minimize(lambda x: tuple(np.asarray(v, float) for v in neg(jnp.asarray(x), u_b, u_i)),
                          np.clip(np.log(phi0), bounds[:, 0], bounds[:, 1]), jac=True,
                          method="L-BFGS-B", bounds=bounds)
        if not res.success:  # (without a discrepancy a step can put the FE interior in the skull)
            print(f"mismatch.py: the parameters' conditional mode was not found: {res.message}",
                  file=sys.stderr)
            continue
        phi = full.copy()
        phi[np.asarray(post.free_index)] = np.exp(res.x)
        out[k] = phi[:g] / phi[g:]
    return out


def posterior_mean_u(path: Path, problem, draws: int = 30, seed: int = 0):
    """Every node's displacement ``(N, 3)`` mm averaged over ``draws`` draws of the run's
    ``posterior.nc`` (``u_b``, and ``u_i`` the FE solve at the draw's parameters plus its
    discrepancy ``d``)."""
    import arviz as az
    import jax
    import jax.numpy as jnp

    from bayesreg.inference.targets import logdensity_fn
    from bayesreg.model.posterior import full_displacement

    post = problem.posterior
    p = az.from_netcdf(path / "posterior.nc").posterior
    lp = logdensity_fn(post, rtol=1e-10, maxiter=5000)
    fe = jax.jit(lambda u_b, phi: _fe_interior(post, lp, u_b, phi))
    names = [n for n in ("lam", "mu") if n in p]
    rng, total = np.random.default_rng(seed), 0.0
    for _ in range(draws):
        c, k = rng.integers(p.sizes["chain"]), rng.integers(p.sizes["draw"])
        u_b = p.u_b.values[c, k]
        phi = np.concatenate([np.atleast_1d(p[n].values[c, k]) for n in names])
        u_i = np.asarray(fe(jnp.asarray(u_b), jnp.asarray(phi))) + (p.d.values[c, k] if "d" in p else 0.0)
        total = total + np.asarray(full_displacement(post, u_b, u_i))
    return total / draws


def _by_tissue(r):
    names = ("csf", "gm", "wm") if len(r) == 3 else tuple(f"group{i}" for i in range(len(r)))
    return dict(zip(names, np.asarray(r).tolist()))


def row(path: Path) -> dict:
    info = json.loads((path / "run.json").read_text())
    errors = info["errors"]
    ckpt = Checkpoint(path)
    data = ckpt.load_problem()
    mesh, truth = data.mesh, data.truth
    w, in_mesh = interpolation_matrix(mesh, data.f)
    brain = np.isin(data.labels.data.ravel(), TISSUE_LABELS) & np.ravel(in_mesh)
    w = sp.csr_matrix(w)[brain]
    true_v = (truth.field.data.reshape(-1, 3)[brain] if truth.field is not None
              else w @ truth.u)

    def mse(v):
        return float(np.mean(np.sum((v - true_v) ** 2, axis=1)))

    free = mesh_best_fit(w, true_v, truth.u)
    ratio = {k: v["median"] for k, v in errors["ratio"].items()}
    lam_t = np.array([ratio.get(t, 1.0) for t in ("csf", "gm", "wm")])
    bound_post = mse(elastic_fit(mesh, w, true_v, lam_t, np.ones(3)))
    scan = {r: mse(elastic_fit(mesh, w, true_v, np.full(3, r), np.ones(3)))
            for r in (1e-3, 0.1, 1.0, 10.0, 100.0)}
    edge = [k for k, v in (info.get("identification") or {}).items() if v.get("at_prior_edge")]
    problem = at_start(assemble(ckpt.load_config(), data), ckpt.load_config(), ckpt.load_init())
    given_truth, given_mean = parameters_given(
        problem, [np.asarray(truth.u), posterior_mean_u(path, problem)],
        np.asarray(problem.posterior.phi_ref))
    return {
        "run": path.name, "t_s_prior": info["config"]["model"].get("t_s_prior"),
        "mse": errors["brain"]["mse_mm2"], "q95_boundary": {
            "posterior_mean": errors["boundary_posterior_mean_mm"]["q95"],
            "start": errors["boundary_initial_mm"]["q95"],
            "reference": errors.get("boundary_reference_mm", {}).get("q95")},
        "coverage_moving_90": (errors.get("coverage_moving") or {}).get("0.9"),
        "coverage_boundary_90": errors["coverage_boundary"]["0.9"],
        "ratio": ratio, "at_prior_edge": edge, "bound_posterior_median": bound_post,
        "bound_scan": scan, "bound_free_nodes": mse(w @ free),
        "reference": reference_method(errors),
        "ratio_given_truth": _by_tissue(given_truth), "ratio_given_mean": _by_tissue(given_mean),
        "converged": info["sampler"]["converged"], "sampling_s": info["timings_s"].get("sampling_s"),
    }


def _gm_wm(ratio):
    return f"{ratio.get('gm', float('nan')):.3g}, {ratio.get('wm', float('nan')):.3g}"


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("runs", nargs="+", type=Path)
    args = ap.parse_args(argv)
    bayesreg.configure_jax()
    rows = [row(p) for p in args.runs]
    print("| run | T_s | brain MSE mm^2: posterior / start / reference | boundary q95 mm: posterior / reference "
          "| 90% coverage moving / boundary | lam/mu GM, WM | on prior edge | FE bound: at posterior "
          "median / best common ratio / free nodes | lam/mu GM, WM given the truth's u / the "
          "posterior mean's |")
    print("|" + "---|" * 10)
    for r in rows:
        m, q = r["mse"], r["q95_boundary"]
        best = min(r["bound_scan"].items(), key=lambda kv: kv[1])
        ts = "fixed" if r["t_s_prior"] is None else f"Gamma({r['t_s_prior']['shape']}, {r['t_s_prior']['rate']})"
        print(f"| {r['run']} | {ts} | {m['posterior_mean']:.4f} / {m['start']:.4f} / {m['reference']:.4f} "
              f"({r['reference']}) | {q['posterior_mean']:.3f} / {q['reference']:.3f} | {r['coverage_moving_90']:.2f} / "
              f"{r['coverage_boundary_90']:.2f} | {r['ratio'].get('gm', float('nan')):.3g}, "
              f"{r['ratio'].get('wm', float('nan')):.3g} | {', '.join(r['at_prior_edge']) or '-'} "
              f"| {r['bound_posterior_median']:.4f} / {best[1]:.4f} (lam/mu {best[0]:g}) / "
              f"{r['bound_free_nodes']:.4f} | {_gm_wm(r['ratio_given_truth'])} / "
              f"{_gm_wm(r['ratio_given_mean'])} |")
    return rows


if __name__ == "__main__":
    main()

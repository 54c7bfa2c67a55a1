"""Calibration of the posterior on truths drawn from its own prior (coverage and ranks).

Nominal coverage of a Bayesian interval is a promise averaged over truths drawn from the
prior, not at one chosen truth (the paper's Sec. 4.1 truth is an energy minimiser with CSF
a void, see ``ratio_profile.py``).  This script checks that promise in the style of
simulation-based calibration (Talts et al. 2018, "Validating Bayesian inference algorithms
with simulation-based calibration", arXiv:1804.06788):

1. draw the elastic parameters from their scaled Beta priors (paper Eq. 11), per tissue;
2. draw the boundary displacements from the elastic prior given them, a Gaussian with
   precision ``S(lam, mu) / T_r`` (``S`` the Schur complement of ``K`` on the boundary
   DOFs, Eqs. 7 and 12), with no component along the six rigid-body modes (where the prior
   is flat), and the interior from the FE solve; a draw that puts a node in the skull or
   inverts an element is redrawn whole (the model's prior is truncated there: hard
   constraints, Sec. 3.2);
3. make ``m`` by warping ``f`` through that deformation (as for every synthetic case);
4. sample the posterior with the configured kernel and normaliser, from a start that does
   not use the truth (``init.fraction=0``: the mode search starts at the identity);
5. record, per estimand (``lam``, ``mu`` and ``lam/mu`` per tissue), whether the truth lies in
   the central 90% interval and its rank among ``L`` draws thinned evenly from the pooled
   chains; for the deformation, the fraction of boundary coordinates whose truth lies in
   their 90% interval.

Under a calibrated posterior every estimand's truth is inside its 90% interval in 90% of
replicas and the ranks are uniform on ``0..L``.  By default the data are noiseless (like the
paper's synthetic images and every synthetic case here): the check is then the practical one
(noiseless synthetic images, the posterior as defined), not an exact SBC, because noiseless
data are not a draw from the likelihood.  Under ``prior_normaliser: paper`` the truths are
the same, with ``mu_GM`` fixed at its true value (as the paper fixes it).

``--noise`` makes the check an exact SBC.  The likelihood ``exp(-E_s / T_s)`` (Eqs. 1 and 9)
sees ``f`` only through its values ``f_q`` at the fixed quadrature points ``x_q`` of the
undeformed mesh, and reads them as independent Gaussian observations,
``f_q ~ N(m(x_q + u(x_q)), T_s / (2 w_q))`` with ``w_q`` the point's weight (mm^3) and ``m``
trilinear (:func:`bayesreg.similarity.moving_values`, which ``ssd_residuals`` uses).
``--noise`` replaces ``f_q`` by one draw of exactly that: ``m`` at the truth's displaced
points plus that noise.  The data are
then drawn from the model itself (prior, then likelihood), and every rank is uniform for a
correct sampler.  Two departures remain, both small here: the truth has no rigid-body part
(the prior is flat along those six modes, so no draw exists), and the prior's truncation by
the hard constraints changes its normaliser by the probability of a valid draw (accepted at
the first or second try in every replica so far).

``--warp-1mm`` makes ``m`` from the 1 mm template instead (then anti-aliased and resampled
onto ``f``'s grid, as ``f`` itself was made): the warp's interpolation error is then that
of the 1 mm grid, not of the 2 mm grid that the likelihood reads.

Run: ``python benchmarks/coverage.py --replicas 0:8 [--normaliser exact|paper] [--set k=v]``
writes one ``replica-<normaliser>-<k>.json`` per replica into ``--out``; replicas may run in
parallel processes (their dataset, the mesh and ``f``, is built once and cached in
``benchmarks/.cache``); ``python benchmarks/coverage.py --summarise DIR`` writes
``coverage.json`` and ``coverage.md`` from every replica file in ``DIR``.  A replica takes
about 4.5 minutes on one core of a 2-core CPU under ``exact`` (2.5 under ``paper``).
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import numpy as np

from bayesreg import _xla

_xla.configure()

import arviz as az  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import scipy.linalg as sla  # noqa: E402
import scipy.ndimage as ndi  # noqa: E402
import scipy.sparse.linalg as spla  # noqa: E402

from bayesreg import labels as L  # noqa: E402
from bayesreg import pipeline  # noqa: E402
from bayesreg.config import load_config  # noqa: E402
from bayesreg.fem import stiffness_matrix  # noqa: E402
from bayesreg.images import Image, interpolate_numpy, mni152, to_reference_grid  # noqa: E402
from bayesreg.mesh import signed_volumes  # noqa: E402
from bayesreg.posterior import elastic_groups, full_displacement  # noqa: E402
from bayesreg.similarity import moving_values  # noqa: E402
from bayesreg.synthetic import Truth, warp_image  # noqa: E402

import samplers  # noqa: E402  (benchmarks/samplers.py: the cached problem)

REPO = Path(__file__).resolve().parents[1]
CONFIG = REPO / "configs" / "quickstart.yaml"
#: the model of the check: a coarse mesh, every tissue's parameters from one proper prior
#: (lam/mu 0.6-100, E_r's scale where a prior draw moves the boundary by a few mm), no
#: smooth skull barrier (the prior is then exactly Gaussian x constraints), a fixed number
#: of draws (no early stop)
DEFAULTS = [
    "mesh.edge_length_mm=32", "model.t_r=100", "model.skull_barrier_mm=0",
    "model.prior_lam.a=2", "model.prior_lam.b=2", "model.prior_lam.r1=2", "model.prior_lam.r2=60",
    "model.prior_mu.a=2", "model.prior_mu.b=2", "model.prior_mu.r1=0.6", "model.prior_mu.r2=3",
    "model.initial_lam.csf=10", "model.initial_lam.gm=10", "model.initial_lam.wm=10",
    "init.fraction=0", "init.start=between", "init.method=mode",
    "sampler.kind=nuts", "sampler.max_tree_depth=6", "sampler.elastic_moves=24",
    "sampler.warmup_steps=200", "sampler.min_draws=200", "sampler.max_draws=200",
    "sampler.chunk_draws=100", "sampler.thinning=1", "sampler.chains=2", "output.progress=false",
]
NORMALISERS = {"exact": ["model.prior_normaliser=exact", "model.fixed=null"],
               "paper": ["model.prior_normaliser=paper"]}
LEVEL = 0.90
RANKS = 99  # draws per replica for the rank statistic (ranks 0..99)


def draw_truth(rng, problem, cfg, *, max_tries: int = 500):
    """One draw of ``(lam, mu)`` per tissue and of ``u`` ``(N, 3)`` mm from the prior.

    Returns ``(lam (3,), mu (3,), u (N, 3), tries)``.  Raises ``RuntimeError`` after
    ``max_tries`` draws that all violate a constraint (lower ``model.t_r``).
    """
    mesh, post = problem.mesh, problem.posterior
    n = mesh.nodes.shape[0]
    b = np.asarray(post.boundary)
    i = np.setdiff1d(np.arange(n), b)
    dof = lambda nodes: (3 * nodes[:, None] + np.arange(3)).ravel()  # noqa: E731
    db, di = dof(b), dof(i)
    rigid = np.asarray(post.rigid_b)  # (3 n_b, 6), orthonormal rigid-body modes
    project = np.eye(len(db)) - rigid @ rigid.T
    priors = [(p.a, p.b, p.r1, p.r2) for p in (cfg.model.prior_lam, cfg.model.prior_mu)]
    for tries in range(1, max_tries + 1):
        lam, mu = (r1 + (r2 - r1) * rng.beta(a, bb, size=3) for a, bb, r1, r2 in priors)
        if cfg.model.fixed is not None:  # the paper's fixed parameter keeps its value
            fx = cfg.model.fixed
            (lam if fx.param == "lam" else mu)[L.TISSUES.index(fx.group)] = fx.value
        k = stiffness_matrix(mesh.nodes, mesh.tets, lam[mesh.tissue], mu[mesh.tissue]).tocsc()
        k_ii, k_ib, k_bb = k[di][:, di], k[di][:, db], k[db][:, db].toarray()
        lu = spla.splu(k_ii.tocsc())
        h = -lu.solve(k_ib.toarray())  # interior map, u_i = H u_b
        s = k_bb + k_ib.T @ h  # Schur complement K_bb - K_bi K_ii^-1 K_ib
        s = project @ (0.5 * (s + s.T)) @ project
        w, v = sla.eigh(s)
        keep = w > 1e-9 * w.max()  # the six rigid-body modes have w ~ 0
        if keep.sum() != len(db) - 6:
            raise RuntimeError(f"Schur complement has {len(db) - keep.sum()} null modes, expected 6")
        u_b = v[:, keep] @ (np.sqrt(cfg.model.t_r / w[keep]) * rng.standard_normal(keep.sum()))
        u = np.zeros((n, 3))
        u[b] = u_b.reshape(-1, 3)
        u[i] = (h @ u_b).reshape(-1, 3)
        inverted = np.sum(signed_volumes(mesh.nodes + u, mesh.tets) <= 0)
        in_skull = np.sum(interpolate_numpy(problem.labels, mesh.nodes + u, order=0, cval=L.SKULL) == L.SKULL)
        if inverted == 0 and in_skull == 0:
            return lam, mu, u, tries
    raise RuntimeError(f"no valid prior draw in {max_tries} tries: lower model.t_r")


def _truth_overrides(lam, mu):
    return [f"synthetic.{p}.{g}={float(v)!r}" for p, vals in (("lam", lam), ("mu", mu))
            for g, v in zip(L.TISSUES, vals)]


def warp_at_1mm(f, mesh, intensity_scale, cfg, u):
    """``m`` warped from the 1 mm MNI template, then brought to ``f``'s grid the way ``f``
    was (Gaussian anti-aliasing of sigma 0.5 voxels, trilinear): a synthetic ``m`` without
    the second interpolation at the likelihood's own resolution.

    ``f``: the problem's (scaled) pre-operative image; ``intensity_scale``: what the
    template was divided by; ``u`` ``(N, 3)`` mm: the nodal displacements of ``mesh``.
    """
    t1 = mni152(1.0, margin_mm=4 * cfg.data.skull_margin_mm)[0]
    f1 = Image(np.asarray(t1.data) / intensity_scale, t1.affine)
    m1 = warp_image(f1, mesh, u, background=0.0, outside=cfg.synthetic.outside)
    m1 = Image(ndi.gaussian_filter(np.asarray(m1.data), 0.5), m1.affine)
    return to_reference_grid(m1, f, name="m (1 mm)", reference_name="f", order=1)


def with_likelihood_draw(rng, problem, u):
    """``problem`` with ``f``'s quadrature values drawn from the likelihood at the truth ``u``.

    Parameters
    ----------
    rng : numpy.random.Generator
    problem : bayesreg.pipeline.Problem
    u : (N, 3) array
        True displacement of every node, world mm.

    Returns
    -------
    problem : Problem
        A copy whose ``posterior.ssd.f_q`` ``(M, Q)`` is ``m(x_q + u(x_q)) + e_q``,
        ``e_q ~ N(0, T_s / (2 w_q))``: the observation model of ``exp(-E_s / T_s)``
        (paper Eqs. 1 and 9), with ``m(x_q + u(x_q))`` from
        :func:`bayesreg.similarity.moving_values`, the log-density's own.  ``problem.f``
        (the image) is left as it was.
    """
    post = problem.posterior
    term = post.ssd
    m_q = np.asarray(moving_values(term, jnp.asarray(u)[post.tets]))
    sd = np.sqrt(0.5 / float(post.inv_t_s)) / np.asarray(term.sqrt_w)
    f_q = m_q + sd * rng.standard_normal(m_q.shape)
    return problem._replace(posterior=post._replace(ssd=term._replace(f_q=jnp.asarray(f_q))))


def run_replica(k: int, args, base_problem) -> dict:
    """Draw truth ``k`` (seed ``args.seed + k``), sample it, return the replica's record."""
    overrides = DEFAULTS + NORMALISERS[args.normaliser] + args.set
    rng = np.random.default_rng([args.seed, k])
    # the truths are drawn with every parameter free (as under exact), for either normaliser
    cfg_draw = load_config(args.config, overrides=DEFAULTS + NORMALISERS["exact"] + args.set)
    t0 = time.perf_counter()
    lam, mu, u, tries = draw_truth(rng, base_problem, cfg_draw)
    extra = _truth_overrides(lam, mu) + [f"seed={args.seed + k}"]
    if args.normaliser == "paper":  # the paper fixes mu_GM (Sec. 3.3): at its true value here
        extra.append(f"model.fixed.value={float(mu[1])!r}")
    cfg = load_config(args.config, overrides=overrides + extra)
    mesh = base_problem.mesh
    f = base_problem.f
    if args.warp_1mm:
        m = warp_at_1mm(f, mesh, base_problem.intensity_scale, cfg, u)
    else:
        m = warp_image(f, mesh, u, background=0.0, outside=cfg.synthetic.outside)
    truth = Truth(u, lam[mesh.tissue], mu[mesh.tissue], np.zeros(0, np.int64))
    data = {"f": f, "m": m, "labels": base_problem.labels, "mesh": mesh, "truth": truth,
            "truth_info": {"truth": "prior draw", "tries": tries}, "n_skull_carved": base_problem.n_skull_carved,
            "intensity_scale": base_problem.intensity_scale, "timings": {}}
    problem = pipeline.assemble(cfg, data)
    if args.noise:
        problem = with_likelihood_draw(rng, problem, u)
    t_truth = time.perf_counter() - t0
    init = pipeline.initialise(problem, cfg)
    result, init = pipeline.sample_problem(problem, cfg, init)
    post = problem.posterior
    nb3 = 3 * post.n_boundary
    draws = np.asarray(result.positions)  # (C, D, dim)
    lam_g, mu_g = (np.asarray(a) for a in elastic_groups(post, draws[..., nb3:]))
    est = {}
    for j, g in enumerate(problem.layout.group_names):
        est[f"lam/mu[{g}]"] = (lam_g[..., j] / mu_g[..., j], lam[j] / mu[j])
        est[f"lam[{g}]"] = (lam_g[..., j], lam[j])
        est[f"mu[{g}]"] = (mu_g[..., j], mu[j])
    lo, hi = (1 - LEVEL) / 2, (1 + LEVEL) / 2
    record = {"replica": k, "normaliser": args.normaliser, "seed": args.seed + k, "warp_1mm": args.warp_1mm,
              "noise": args.noise, "overrides": list(args.set),
              "n_nodes": int(mesh.nodes.shape[0]), "n_boundary": int(post.n_boundary),
              "truth": {"lam": lam.tolist(), "mu": mu.tolist(), "tries": tries,
                        "u_b_rms_mm": float(np.sqrt(np.mean(u[np.asarray(post.boundary)] ** 2))),
                        "u_max_mm": float(np.abs(u).max())},
              "chains": int(draws.shape[0]), "draws_per_chain": int(draws.shape[1]),
              "wall_s": {"truth_and_posterior": t_truth, **{k: float(v) for k, v in result.timings.items()},
                         "total": time.perf_counter() - t0},
              "estimands": {}}
    pooled_idx = np.linspace(0, draws.shape[0] * draws.shape[1] - 1, RANKS).round().astype(int)
    for name, (x, true) in est.items():
        fx = cfg.model.fixed
        if fx is not None and name == f"{fx.param}[{fx.group}]":
            continue  # held at its truth, not sampled
        flat = x.reshape(-1)
        q = np.quantile(flat, [lo, 0.5, hi])
        record["estimands"][name] = {
            "truth": float(true), "median": float(q[1]), "q05": float(q[0]), "q95": float(q[2]),
            "inside": bool(q[0] <= true <= q[2]),
            "rank": int(np.sum(flat[pooled_idx] < true)),
            "rhat": float(az.rhat(x, method="rank")), "ess_bulk": float(az.ess(x, method="bulk")),
        }
    # the strain energy of each tissue under the true parameters: truth against thinned draws
    # (a posterior whose deformations are smoother than the truth in one tissue raises that
    # tissue's stiffness)
    interior = np.asarray(result.interior).reshape(-1, *np.asarray(result.interior).shape[2:])
    k_tissue = [stiffness_matrix(mesh.nodes, mesh.tets, np.where(mesh.tissue == t, lam[mesh.tissue], 0.0),
                                 np.where(mesh.tissue == t, mu[mesh.tissue], 0.0)) for t in range(3)]
    energy = lambda uu: [0.5 * float(uu.ravel() @ (k @ uu.ravel())) for k in k_tissue]  # noqa: E731
    e_true = energy(u)
    e_draws = np.array([energy(np.asarray(full_displacement(post, draws.reshape(-1, draws.shape[-1])[d, :nb3]
                                                              .reshape(-1, 3), interior[d])))
                        for d in pooled_idx])
    record["strain_energy_at_true_parameters"] = {
        g: {"truth": e_true[t], "draws_median": float(np.median(e_draws[:, t])),
            "rank": int(np.sum(e_draws[:, t] < e_true[t]))} for t, g in enumerate(L.TISSUES)}
    u_draws = draws[..., :nb3].reshape(-1, nb3)
    qu = np.quantile(u_draws, [lo, hi], axis=0)
    u_true = u[np.asarray(post.boundary)].reshape(-1)
    record["u_b"] = {"fraction_inside": float(np.mean((qu[0] <= u_true) & (u_true <= qu[1]))),
                     "rmse_mm": float(np.sqrt(np.mean((u_draws.mean(0) - u_true) ** 2))),
                     "rhat_max": float(np.nanmax(np.asarray(az.rhat(draws[..., :nb3], method="rank"))))}
    return record


def _write_atomic(path: Path, text: str) -> None:
    tmp = path.with_name(path.name + f".tmp{os.getpid()}")
    tmp.write_text(text)
    os.replace(tmp, path)


def _data_kind(record: dict) -> str:
    """How a replica's data were made (older records lack the keys: noiseless 2 mm warp)."""
    extra = "".join(f", {o}" for o in record.get("overrides", []))
    if record.get("noise"):
        return "drawn from the likelihood (exact SBC)" + extra
    return "noiseless, " + ("1 mm warp" if record.get("warp_1mm") else "2 mm warp") + extra


def summarise(folder: Path) -> dict:
    """Coverage per normaliser and estimand over every ``replica-*.json`` in ``folder``."""
    recs = [json.loads(p.read_text()) for p in sorted(folder.glob("replica-*.json"))]
    if not recs:
        raise FileNotFoundError(f"no replica-*.json in {folder}")
    out = {}
    for norm in sorted({r["normaliser"] for r in recs}):
        rs = [r for r in recs if r["normaliser"] == norm]
        names = list(rs[0]["estimands"])
        rows = {}
        for name in names:
            e = [r["estimands"][name] for r in rs if name in r["estimands"]]
            n = len(e)
            inside = sum(x["inside"] for x in e)
            ranks = np.array([x["rank"] for x in e])
            # ranks in 0..RANKS, binned in 4: chi-square against uniform (3 dof)
            counts = np.histogram(ranks, bins=4, range=(0, RANKS + 1))[0]
            expect = n / 4
            rows[name] = {"n": n, "inside": inside, "coverage": inside / n,
                          "binomial_sd": float(np.sqrt(LEVEL * (1 - LEVEL) / n)),
                          "rank_quartile_counts": counts.tolist(),
                          "rank_chi2_3dof": float(np.sum((counts - expect) ** 2 / expect)),
                          "median_rel_error": float(np.median([x["median"] / x["truth"] - 1 for x in e])),
                          "rhat_max": float(max(x["rhat"] for x in e)),
                          "ess_bulk_min": float(min(x["ess_bulk"] for x in e))}
        u_frac = [r["u_b"]["fraction_inside"] for r in rs]
        kinds = sorted({_data_kind(r) for r in rs})
        out[norm] = {"replicas": len(rs), "data": " + ".join(kinds),
                     "n_nodes": rs[0]["n_nodes"], "n_boundary": rs[0]["n_boundary"],
                     "draws": f"{rs[0]['chains']} x {rs[0]['draws_per_chain']}",
                     "wall_s_median": float(np.median([r["wall_s"]["total"] for r in rs])),
                     "u_b_fraction_inside_mean": float(np.mean(u_frac)),
                     "u_b_rmse_mm_median": float(np.median([r["u_b"]["rmse_mm"] for r in rs])),
                     "u_b_rhat_max": float(max(r["u_b"]["rhat_max"] for r in rs)),
                     "truth_u_max_mm_median": float(np.median([r["truth"]["u_max_mm"] for r in rs])),
                     "estimands": rows}
    lines = [f"# Coverage of the {LEVEL:.0%} intervals on truths drawn from the prior", "",
             "`python benchmarks/coverage.py --summarise` of the replica files in this folder; "
             "see the script's docstring for the design.", ""]
    for norm, s in out.items():
        lines += [f"## prior_normaliser: {norm}", "",
                  f"{s['replicas']} replicas, data {s['data']}, {s['n_nodes']} nodes ({s['n_boundary']} boundary), "
                  f"{s['draws']} draws each, median wall {s['wall_s_median']:.0f} s; truth's max |u| "
                  f"median {s['truth_u_max_mm_median']:.1f} mm.  Boundary coordinates inside their "
                  f"90% interval: {s['u_b_fraction_inside_mean']:.1%} on average (RMSE of the mean "
                  f"{s['u_b_rmse_mm_median']:.2f} mm, max rank R-hat {s['u_b_rhat_max']:.2f}).", "",
                  "| estimand | truth inside 90% | coverage (binomial sd) | rank quartiles | chi2 (3 dof) "
                  "| median rel. error of the median | max R-hat | min bulk ESS |",
                  "|---|---|---|---|---|---|---|---|"]
        for name, r in s["estimands"].items():
            lines.append(f"| {name} | {r['inside']} / {r['n']} | {r['coverage']:.2f} ({r['binomial_sd']:.2f}) | "
                         f"{' '.join(map(str, r['rank_quartile_counts']))} | {r['rank_chi2_3dof']:.1f} | "
                         f"{r['median_rel_error']:+.1%} | {r['rhat_max']:.2f} | {r['ess_bulk_min']:.0f} |")
        lines.append("")
    _write_atomic(folder / "coverage.json", json.dumps(out, indent=2))
    _write_atomic(folder / "coverage.md", "\n".join(lines))
    print("\n".join(lines))
    return out


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--config", type=Path, default=CONFIG)
    p.add_argument("--normaliser", choices=sorted(NORMALISERS), default="exact")
    p.add_argument("--replicas", default="0:4", help="replica indices START:STOP[:STEP] (a Python range)")
    p.add_argument("--seed", type=int, default=2026)
    p.add_argument("--set", action="append", default=[], help="config override (repeatable)")
    p.add_argument("--out", type=Path, default=REPO / "runs" / "coverage")
    p.add_argument("--cache", type=Path, default=REPO / "benchmarks" / ".cache")
    p.add_argument("--warp-1mm", action="store_true",
                   help="make m from the 1 mm MNI template (mni152 data only), then bring it to f's grid")
    p.add_argument("--noise", action="store_true",
                   help="exact SBC: f's quadrature values drawn from the likelihood at the truth")
    p.add_argument("--summarise", type=Path, metavar="DIR", help="only summarise the replicas in DIR")
    args = p.parse_args(argv)
    if args.summarise is not None:
        summarise(args.summarise)
        return
    replicas = range(*(int(x) for x in args.replicas.split(":")))
    cfg = load_config(args.config, overrides=DEFAULTS + NORMALISERS["exact"] + args.set)
    base, cached = samplers.problem_for(cfg, args.cache, prefix="coverage")
    print(f"dataset {'from cache' if cached else 'built'}: {base.mesh.nodes.shape[0]} nodes, "
          f"{base.posterior.n_boundary} boundary", flush=True)
    args.out.mkdir(parents=True, exist_ok=True)
    for k in replicas:
        path = args.out / f"replica-{args.normaliser}-{k:03d}.json"
        if path.is_file():
            print(f"replica {k}: exists, skipped", flush=True)
            continue
        rec = run_replica(k, args, base)
        _write_atomic(path, json.dumps(rec, indent=2))
        ins = {n: e["inside"] for n, e in rec["estimands"].items() if n.startswith("lam/mu")}
        print(f"replica {k}: {rec['wall_s']['total']:.0f} s, truth lam {np.round(rec['truth']['lam'], 2)} "
              f"mu {np.round(rec['truth']['mu'], 2)}, max |u| {rec['truth']['u_max_mm']:.1f} mm, "
              f"ratios inside {ins}, u_b inside {rec['u_b']['fraction_inside']:.2f}", flush=True)


if __name__ == "__main__":
    main()

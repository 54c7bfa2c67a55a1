"""What each similarity term costs, per mesh size: SSD (the paper's) against LNCC.

Run from the repository root (not part of the test suite)::

    python benchmarks/similarity.py                  # the quickstart's 24 mm mesh on 2 mm images
    python benchmarks/similarity.py --meshes 26@3    # a coarse mesh on 3 mm images (a minute)
    python benchmarks/similarity.py --windows 6,9,12 # LNCC's window sides (mm)

On each mesh (the cached problems of ``benchmarks/run.py``: the MNI152 brain, a smooth
synthetic shift; the quickstart's quadrature level) and at the truth, for SSD and for LNCC
with each window side:

* ``value+grad ms``: the term's value and gradient with respect to the nodal displacements,
  jitted, median of repeated calls at nearby displacements (what a leapfrog step adds);
* ``gram s``: its Gauss-Newton Gram matrix ``J^T J`` (the Laplace proposal's, once per run);
* ``E rest``, ``E truth``: the term at the rest state and at the truth;
* ``T_s matching SSD``: the temperature at which the term's Gauss-Newton curvature at the
  truth (the trace of ``J^T J / T_s``) equals SSD's at the config's ``model.t_s``: where
  LNCC's default ``model.lncc.t_s`` comes from.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

import bayesreg

sys.path.insert(0, str(Path(__file__).resolve().parent))
from normaliser import time_cycling  # noqa: E402
from run import DEFAULT_CONFIG, cached_data, log, mesh_overrides, parse_mesh  # noqa: E402


def bench_term(name, term, mesh, u, args) -> dict:
    """One term's row; ``trace`` is its Gauss-Newton curvature at ``u``."""
    tets = jnp.asarray(mesh.tets)
    vg = jax.jit(jax.value_and_grad(lambda v: term.energy(v[tets])))
    rng = np.random.default_rng(0)
    inputs = [jnp.asarray(u + 0.05 * rng.normal(size=u.shape)) for _ in range(16)]
    ms = 1e3 * time_cycling(vg, inputs, target_s=args.time_target_s)
    t0 = time.perf_counter()
    gram = term.gram(u, mesh.tets, len(mesh.nodes))
    gram_s = time.perf_counter() - t0
    row = {"term": name, "ms": ms, "gram_s": gram_s, "trace": float(gram.diagonal().sum()),
           "e_rest": float(term.energy(jnp.zeros_like(jnp.asarray(u))[tets])),
           "e_truth": float(term.energy(jnp.asarray(u)[tets]))}
    log(f"  {name}: {ms:.2f} ms value+grad, gram {gram_s:.1f} s")
    return row


def bench_mesh(edge: float, res: float, args) -> dict:
    from bayesreg.config import load_config
    from bayesreg.data import labels as L
    from bayesreg.data.images import Image
    from bayesreg.model.lncc import build_lncc
    from bayesreg.model.problem import assemble

    cfg = load_config(DEFAULT_CONFIG, overrides=mesh_overrides(edge, res))
    data, cached = cached_data(cfg, args.cache, f"similarity-e{edge:g}-r{res:g}", args.rebuild)
    problem = assemble(cfg, data)
    mesh, ssd = problem.mesh, problem.posterior.similarity
    u = np.asarray(data.truth.u)
    log(f"mesh {edge:g} mm on {res:g} mm images: {len(mesh.nodes)} nodes, "
        f"{ssd.n_observations} quadrature points{' (cached)' if cached else ''}")
    rows = [bench_term("ssd", ssd, mesh, u, args)]
    reach = Image((data.labels.data != L.SKULL).astype(np.uint8), data.labels.affine)
    for w in args.windows:
        term = build_lncc(mesh.nodes, mesh.tets, data.f, data.m, window_mm=w, eps=cfg.model.lncc.eps,
                          quadrature_level=cfg.model.quadrature_level, reach=reach,
                          moving_dtype=cfg.model.moving_dtype, interpolation=cfg.model.interpolation)
        row = bench_term(f"lncc {w:g} mm", term, mesh, u, args)
        row["windows"] = int(term.sqrt_w.shape[0])
        row["pairs"] = int(term.point.shape[0])
        rows.append(row)
    for row in rows:  # the temperature giving each term SSD's curvature at model.t_s
        row["t_s_matching"] = cfg.model.t_s * row["trace"] / rows[0]["trace"]
    return {"edge_mm": edge, "resolution_mm": res, "nodes": len(mesh.nodes),
            "points": ssd.n_observations, "rows": rows}


def table(results) -> str:
    lines = ["| mesh (nodes, points) | term (windows, pairs) | value+grad ms | gram s | E rest | "
             "E truth | T_s matching SSD |", "|---" * 7 + "|"]
    for r in results:
        mesh = f"{r['edge_mm']:g} mm @ {r['resolution_mm']:g} mm ({r['nodes']}, {r['points']})"
        for t in r["rows"]:
            term = t["term"] + (f" ({t['windows']}, {t['pairs']})" if "windows" in t else "")
            lines.append(f"| {mesh} | {term} | {t['ms']:.2f} | {t['gram_s']:.2f} | {t['e_rest']:.4g} | "
                         f"{t['e_truth']:.4g} | {t['t_s_matching']:.3g} |")
    return "\n".join(lines)


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--meshes", default="24", help="EDGE[@RESOLUTION] mm, comma-separated")
    p.add_argument("--windows", default="9", help="LNCC window sides (mm), comma-separated")
    p.add_argument("--time-target-s", type=float, default=2.0)
    p.add_argument("--cache", type=Path, default=Path(__file__).resolve().parent / ".cache")
    p.add_argument("--rebuild", action="store_true")
    args = p.parse_args(argv)
    args.windows = [float(w) for w in args.windows.split(",")]
    bayesreg.configure_jax()
    results = [bench_mesh(*parse_mesh(m), args) for m in args.meshes.split(",")]
    print(table(results))
    return results


if __name__ == "__main__":
    main()

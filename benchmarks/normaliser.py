"""What the exact normaliser of the elastic prior costs a gradient sampler, per mesh size.

Run from the repository root (not part of the test suite)::

    python benchmarks/normaliser.py                  # the quickstart's 24 mm and the paper's 16 mm mesh
    python benchmarks/normaliser.py --meshes 26@3    # a coarse mesh on 3 mm images (a minute)

On each mesh (the cached problems of ``benchmarks/run.py``: the MNI152 brain, a smooth
synthetic shift) the quickstart's model with every parameter free, at the truth, in the
joint target of the NUTS kernel (``u_b`` whitened, the parameters' logits), timed as one
leapfrog step evaluates it (value and gradient, jitted, median of repeated calls):

* ``paper``: without the normaliser (``model.prior_normaliser: paper``), the reference;
* ``exact (surrogate)``: what the default's trajectories evaluate under ``exact``: the
  log-density with the normaliser's smooth surrogate (:func:`bayesreg.fem.normaliser.build_surrogate`);
* ``exact correction``: the exact sparse normaliser less the surrogate, once per transition
  (value only: two sparse Cholesky factorisations);
* ``exact (sparse gradient)``: the log-density with the exact sparse normaliser in every
  leapfrog step (gradient by selected inversion);
* ``dense reference``: the normaliser alone by one dense Cholesky factorisation of ``K``,
  value and gradient (the implementation before the sparse one).

The table gives milliseconds and the ratio to ``paper``; per transition of ``G`` gradients
(NUTS on the quickstart: about 31) the default's cost relative to ``paper`` is
``(G t_surrogate + t_correction) / (G t_paper)``, printed for ``G = 31``.
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
from run import DEFAULT_CONFIG, cached_data, log, mesh_overrides, parse_mesh  # noqa: E402

GRADIENTS_PER_TRANSITION = 31


def time_cycling(fn, inputs, *, target_s: float, min_reps: int = 5) -> float:
    """Median seconds per call of ``fn(x)``, ``x`` cycling through ``inputs`` after two
    warm-up calls: CHOLMOD's factorisations are cached by value (sparsax), so a timing at one
    input would time a cache hit."""
    for x in inputs[:2]:
        jax.block_until_ready(fn(x))
    times, k, t_start = [], 2, time.perf_counter()
    while len(times) < min_reps or time.perf_counter() - t_start < target_s:
        x = inputs[k % len(inputs)]
        k += 1
        t = time.perf_counter()
        jax.block_until_ready(fn(x))
        times.append(time.perf_counter() - t)
    return float(np.median(times))


def _targets(problem, cfg_exact, cfg_paper, theta):
    from bayesreg.sampling.kernels import gibbs
    from bayesreg.sampling.kernels.target import joint_target
    from bayesreg.model.parameters import from_unconstrained, to_unconstrained
    from bayesreg.inference.targets import gradient_target

    post = problem.posterior
    nb3 = 3 * post.n_boundary
    factor = np.ones(nb3)
    t_paper = gradient_target(problem, cfg_paper, theta, factor)
    t0 = time.perf_counter()
    t_exact = gradient_target(problem, cfg_exact, theta, factor)
    build_s = time.perf_counter() - t0
    base = t_exact._replace(correction=None)
    # the same joint target with the exact sparse normaliser in every evaluation
    from bayesreg.inference.targets import dense_preconditioning
    from bayesreg.sampling.kernels.target import make_target

    plain = make_target(post, center_u=theta[:nb3], factor=factor, exact=True, condensed=False,
                        precondition=dense_preconditioning(problem, cfg_exact))
    t_sparse = joint_target(plain, center_eta=to_unconstrained(post.prior, jnp.asarray(theta[nb3:])),
                            eta_scale=cfg_exact.sampler.sigma_eta,
                            log_jacobian=lambda eta: from_unconstrained(post.prior, eta)[1])
    del base
    out = {}
    for name, tg in (("paper", t_paper), ("exact (surrogate)", t_exact),
                     ("exact (sparse gradient)", t_sparse)):
        kernel = gibbs.build_kernel(tg, "nuts")
        state, _ = jax.jit(lambda x, tg=tg: gibbs.init(tg, x, jnp.zeros((post.op.n_interior, 3))))(
            jnp.asarray(theta))
        cache = jax.jit(kernel.init_cache)(state)
        out[name] = (tg, state, cache)
    return out, build_s


def bench_mesh(edge: float, res: float, args) -> dict:
    from bayesreg.config import load_config
    from bayesreg.model.posterior import log_normaliser_dense
    from bayesreg.model.problem import assemble

    extra = ["model.fixed=null"]
    cfg_exact = load_config(DEFAULT_CONFIG, overrides=mesh_overrides(edge, res) + extra
                            + ["model.prior_normaliser=exact"])
    cfg_paper = load_config(DEFAULT_CONFIG, overrides=mesh_overrides(edge, res) + extra
                            + ["model.prior_normaliser=paper"])
    data, cached = cached_data(load_config(DEFAULT_CONFIG, overrides=mesh_overrides(edge, res)),
                               args.cache, f"normaliser-e{edge:g}-r{res:g}", args.rebuild)
    problem = assemble(cfg_exact, data)
    post = problem.posterior
    nb3 = 3 * post.n_boundary
    u_true = np.asarray(data.truth.u)[np.asarray(problem.mesh.boundary)].reshape(-1)
    theta = np.concatenate([u_true, problem.phi_true])
    n = len(problem.mesh.nodes)
    log(f"mesh {edge:g} mm on {res:g} mm images: {n} nodes, {post.n_boundary} boundary"
        f"{' (cached)' if cached else ''}")
    targets, build_s = _targets(problem, cfg_exact, cfg_paper, theta)
    row = {"edge_mm": edge, "resolution_mm": res, "nodes": n, "boundary_nodes": post.n_boundary,
           "surrogate_build_s": build_s, "ms": {}}
    rng = np.random.default_rng(0)
    n_free = post.n_free
    # positions whose parameters' logits differ by about 0.05 (a trajectory's steps)
    steps = [jnp.concatenate([jnp.zeros(nb3), 0.5 * jnp.asarray(rng.normal(size=n_free))])
             for _ in range(64)]
    for name, (tg, state, cache) in targets.items():
        vg = jax.jit(jax.value_and_grad(tg.u_logdensity))
        z = state.u.position
        row["ms"][name] = 1e3 * time_cycling(lambda d: vg(z + d, state.eta, cache, state.interior),
                                             steps, target_s=args.time_target_s)
        log(f"  {name}: {row['ms'][name]:.2f} ms")
    tg, state, _ = targets["exact (surrogate)"]
    corr = jax.jit(tg.correction)
    row["ms"]["exact correction"] = 1e3 * time_cycling(lambda d: corr(state.u.position + d), steps,
                                                       target_s=args.time_target_s)
    dense = jax.jit(jax.value_and_grad(lambda p: log_normaliser_dense(post, p)))
    phis = [jnp.asarray(theta[nb3:]) * jnp.exp(0.05 * d[nb3:]) for d in steps]
    row["ms"]["dense reference"] = 1e3 * time_cycling(dense, phis, target_s=args.time_target_s)
    g = GRADIENTS_PER_TRANSITION
    ms = row["ms"]
    row["per_transition_ratio"] = (g * ms["exact (surrogate)"] + ms["exact correction"]) / (g * ms["paper"])
    return row


def table(rows) -> str:
    names = ["paper", "exact (surrogate)", "exact correction", "exact (sparse gradient)",
             "dense reference"]
    lines = ["| mesh (nodes, boundary) | " + " | ".join(names) + f" | default per transition of "
             f"{GRADIENTS_PER_TRANSITION} gradients | surrogate build s |",
             "|---" * (len(names) + 3) + "|"]
    for r in rows:
        p = r["ms"]["paper"]
        cells = [f"{r['ms'][k]:.2f} ms ({r['ms'][k] / p:.2f}x)" for k in names]
        lines.append(f"| {r['edge_mm']:g} mm @ {r['resolution_mm']:g} mm ({r['nodes']}, "
                     f"{r['boundary_nodes']}) | " + " | ".join(cells)
                     + f" | {r['per_transition_ratio']:.3f}x | {r['surrogate_build_s']:.1f} |")
    return "\n".join(lines)


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--meshes", default="24,16", help="EDGE[@RESOLUTION] mm, comma-separated")
    p.add_argument("--time-target-s", type=float, default=2.0)
    p.add_argument("--cache", type=Path, default=Path(__file__).resolve().parent / ".cache")
    p.add_argument("--rebuild", action="store_true")
    args = p.parse_args(argv)
    bayesreg.configure_jax()
    rows = [bench_mesh(*parse_mesh(m), args) for m in args.meshes.split(",")]
    print(table(rows))
    return rows


if __name__ == "__main__":
    main()

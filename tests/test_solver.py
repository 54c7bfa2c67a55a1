"""Interior CG solve against SciPy's direct solver, warm starts, implicit gradients."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.sparse.linalg as spla

from bayesreg import fem
from bayesreg.solver import solve_interior


def _reference(mesh, lam, mu, ub):
    k = fem.stiffness_matrix(mesh.nodes, mesh.tets, lam, mu)
    idf = (3 * mesh.interior[:, None] + np.arange(3)).ravel()
    bd = (3 * mesh.boundary[:, None] + np.arange(3)).ravel()
    return spla.spsolve(k[idf][:, idf].tocsc(), -(k[idf][:, bd] @ ub.ravel())).reshape(-1, 3)


@pytest.mark.parametrize("csf", [1e-2, 1e-6], ids=["csf1e-2", "csf1e-6-stiff-ratio"])
def test_cg_matches_spsolve_on_brain_mesh(brain, csf):
    _, _, mesh = brain
    lam = np.array([csf, 10.0, 30.0])[mesh.tissue]
    mu = np.array([csf, 1.0, 1.0])[mesh.tissue]
    ub = np.random.default_rng(0).normal(size=(len(mesh.boundary), 3))
    ref = _reference(mesh, lam, mu, ub)
    op, interior = fem.build_operator(mesh.nodes, mesh.tets, mesh.boundary)
    np.testing.assert_array_equal(interior, mesh.interior)
    u_i, info = jax.jit(lambda a, b, c: solve_interior(op, a, b, c, jnp.zeros_like(ref), rtol=1e-13,
                                                       maxiter=5000))(lam, mu, ub)
    assert bool(info.converged)
    err = np.linalg.norm(np.asarray(u_i) - ref) / np.linalg.norm(ref)
    assert err < 1e-8


def test_warm_start_needs_fewer_iterations(brain):
    _, _, mesh = brain
    lam = np.array([1e-2, 10.0, 30.0])[mesh.tissue]
    mu = np.array([1e-2, 1.0, 1.0])[mesh.tissue]
    rng = np.random.default_rng(1)
    ub = rng.normal(size=(len(mesh.boundary), 3))
    op, _ = fem.build_operator(mesh.nodes, mesh.tets, mesh.boundary)
    solve = jax.jit(lambda ub, x0: solve_interior(op, lam, mu, ub, x0))
    x, info_cold = solve(ub, jnp.zeros((op.n_interior, 3)))
    ub2 = ub + 0.01 * rng.normal(size=ub.shape)  # a random-walk-sized move
    _, cold = solve(ub2, jnp.zeros((op.n_interior, 3)))
    _, warm = solve(ub2, x)
    assert bool(cold.converged) and bool(warm.converged)
    assert int(warm.iterations) < int(cold.iterations)


def test_nonconverged_solve_is_reported():
    from conftest import box_mesh

    m = box_mesh((3, 3, 3))
    op, _ = fem.build_operator(m.nodes, m.tets, m.boundary)
    ub = np.random.default_rng(2).normal(size=(len(m.boundary), 3))
    lam = np.full(len(m.tets), 10.0)
    mu = np.ones(len(m.tets))
    _, info = solve_interior(op, lam, mu, ub, jnp.zeros((op.n_interior, 3)), maxiter=1)
    assert not bool(info.converged) and int(info.iterations) == 1
    _, info = solve_interior(op, lam, -mu, ub, jnp.zeros((op.n_interior, 3)), maxiter=200)
    assert not bool(info.converged)  # indefinite K (mu < 0) is never reported converged


def test_gradient_through_solve_matches_finite_differences():
    from conftest import box_mesh

    m = box_mesh((3, 3, 3))
    op, _ = fem.build_operator(m.nodes, m.tets, m.boundary)
    rng = np.random.default_rng(3)
    ub = jnp.asarray(rng.normal(size=(len(m.boundary), 3)))
    w = jnp.asarray(rng.normal(size=(op.n_interior, 3)))

    def f(ub, s):
        lam = jnp.full(len(m.tets), 10.0) * s
        u_i, _ = solve_interior(op, lam, jnp.ones(len(m.tets)), ub, jnp.zeros((op.n_interior, 3)),
                                rtol=1e-13)
        return jnp.sum(w * u_i)

    g_ub, g_s = jax.grad(f, argnums=(0, 1))(ub, 1.3)
    d = jnp.asarray(rng.normal(size=ub.shape))
    h = 1e-5
    fd = (f(ub + h * d, 1.3) - f(ub - h * d, 1.3)) / (2 * h)
    assert float(jnp.sum(g_ub * d)) == pytest.approx(float(fd), rel=1e-6)
    fd_s = (f(ub, 1.3 + h) - f(ub, 1.3 - h)) / (2 * h)
    assert float(g_s) == pytest.approx(float(fd_s), rel=1e-6)

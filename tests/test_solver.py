"""Interior CG solve against SciPy's direct solver, warm starts, implicit gradients."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from bayesreg.fem import stiffness
from bayesreg.fem.preconditioners import DENSE_MAX_ITERATIONS, DensePreconditioner, dense_preconditioner
from bayesreg.fem.solver import interior_map, pcg, solve_interior, solve_interior_blocks
from conftest import box_mesh
from helpers import direct_interior_solve


@pytest.mark.parametrize("csf", [1e-2, 1e-6], ids=["csf1e-2", "csf1e-6-stiff-ratio"])
def test_cg_matches_spsolve_on_brain_mesh(brain, csf):
    _, _, mesh = brain
    lam = np.array([csf, 10.0, 30.0])[mesh.tissue]
    mu = np.array([csf, 1.0, 1.0])[mesh.tissue]
    ub = np.random.default_rng(0).normal(size=(len(mesh.boundary), 3))
    ref = direct_interior_solve(mesh, lam, mu, ub)
    op, interior = stiffness.build_operator(mesh.nodes, mesh.tets, mesh.boundary)
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
    op, _ = stiffness.build_operator(mesh.nodes, mesh.tets, mesh.boundary)
    solve = jax.jit(lambda ub, x0: solve_interior(op, lam, mu, ub, x0))
    x, info_cold = solve(ub, jnp.zeros((op.n_interior, 3)))
    ub2 = ub + 0.01 * rng.normal(size=ub.shape)  # a random-walk-sized move
    _, cold = solve(ub2, jnp.zeros((op.n_interior, 3)))
    _, warm = solve(ub2, x)
    assert bool(cold.converged) and bool(warm.converged)
    assert int(warm.iterations) < int(cold.iterations)


def test_nonconverged_solve_is_reported():
    m = box_mesh((3, 3, 3))
    op, _ = stiffness.build_operator(m.nodes, m.tets, m.boundary)
    ub = np.random.default_rng(2).normal(size=(len(m.boundary), 3))
    lam = np.full(len(m.tets), 10.0)
    mu = np.ones(len(m.tets))
    _, info = solve_interior(op, lam, mu, ub, jnp.zeros((op.n_interior, 3)), maxiter=1)
    assert not bool(info.converged) and int(info.iterations) == 1
    _, info = solve_interior(op, lam, -mu, ub, jnp.zeros((op.n_interior, 3)), maxiter=200)
    assert not bool(info.converged)  # indefinite K (mu < 0) is never reported converged


def test_zero_boundary_displacement_solves_to_zero_from_any_warm_start():
    """``u_b = 0`` (the identity deformation) makes ``b = 0``: the solve converges at once to
    exactly 0 whatever the warm start (a relative tolerance of ``|b| = 0`` could never be
    met)."""
    m = box_mesh((3, 3, 3))
    op, _ = stiffness.build_operator(m.nodes, m.tets, m.boundary)
    lam, mu = np.full(len(m.tets), 10.0), np.ones(len(m.tets))
    warm = np.random.default_rng(3).normal(size=(op.n_interior, 3))
    u_i, info = solve_interior(op, lam, mu, np.zeros((len(m.boundary), 3)), warm)
    assert bool(info.converged) and int(info.iterations) == 0
    np.testing.assert_array_equal(np.asarray(u_i), 0.0)


@pytest.mark.parametrize("preconditioner", ["block-jacobi", "dense"])
def test_gradient_through_solve_matches_finite_differences(preconditioner):
    """Implicit differentiation through the CG (``lax.custom_linear_solve``) in ``u_b`` and
    in a parameter scale, with either preconditioner (the dense one built at other
    parameters, as a chain's preconditioner is), against central differences."""
    m = box_mesh((3, 3, 3))
    op, _ = stiffness.build_operator(m.nodes, m.tets, m.boundary)
    rng = np.random.default_rng(3)
    ub = jnp.asarray(rng.normal(size=(len(m.boundary), 3)))
    w = jnp.asarray(rng.normal(size=(op.n_interior, 3)))
    pre = (dense_preconditioner(op, op.blocks(jnp.full(len(m.tets), 12.0), jnp.ones(len(m.tets)))[0])
           if preconditioner == "dense" else None)

    def f(ub, s):
        b_ii, b_ib = op.blocks(jnp.full(len(m.tets), 10.0) * s, jnp.ones(len(m.tets)))
        u_i, _ = solve_interior_blocks(op, b_ii, b_ib, ub, jnp.zeros((op.n_interior, 3)), rtol=1e-13,
                                       precond=pre)
        return jnp.sum(w * u_i)

    g_ub, g_s = jax.grad(f, argnums=(0, 1))(ub, 1.3)
    d = jnp.asarray(rng.normal(size=ub.shape))
    h = 1e-5
    fd = (f(ub + h * d, 1.3) - f(ub - h * d, 1.3)) / (2 * h)
    assert float(jnp.sum(g_ub * d)) == pytest.approx(float(fd), rel=1e-6)
    fd_s = (f(ub, 1.3 + h) - f(ub, 1.3 - h)) / (2 * h)
    assert float(g_s) == pytest.approx(float(fd_s), rel=1e-6)


def test_a_failing_preconditioned_solve_hands_over_to_block_jacobi():
    """A preconditioner that is no approximation of ``K_ii^-1`` (indefinite) does not turn
    into rejected proposals: after ``DENSE_MAX_ITERATIONS`` the solve continues with block
    Jacobi from its iterate, to the same tolerance."""
    m = box_mesh((3, 3, 3))
    op, _ = stiffness.build_operator(m.nodes, m.tets, m.boundary)
    lam, mu = np.full(len(m.tets), 10.0), np.ones(len(m.tets))
    ub = jnp.asarray(np.random.default_rng(8).normal(size=(len(m.boundary), 3)))
    x0 = jnp.zeros((op.n_interior, 3))
    q = np.linalg.qr(np.random.default_rng(9).normal(size=(3 * op.n_interior,) * 2))[0]
    wrong = DensePreconditioner(jnp.asarray(q @ np.diag(np.linspace(-1, 1, len(q))) @ q.T, jnp.float32),
                                jnp.asarray(False))
    u, info = solve_interior_blocks(op, *op.blocks(lam, mu), ub, x0, rtol=1e-10, precond=wrong)
    expect = direct_interior_solve(m, lam, mu, np.asarray(ub))
    assert bool(info.converged) and int(info.iterations) > DENSE_MAX_ITERATIONS
    assert np.linalg.norm(np.asarray(u) - expect) / np.linalg.norm(expect) < 1e-8


def test_solver_entry_points_check_shapes_statically():
    """Wrong shapes of ``u_b``, the warm start or the parameters are refused with the
    argument and the expected shape named.  The checks are on shapes only: under jit they
    raise at tracing, under vmap they see one chain's shapes (a batch of valid u_b solves)."""
    m = box_mesh((2, 2, 2))
    op, _ = stiffness.build_operator(m.nodes, m.tets, m.boundary)
    n_b, n_i, n_e = len(m.boundary), op.n_interior, len(m.tets)
    lam, mu = np.full(n_e, 10.0), np.ones(n_e)
    ub = np.random.default_rng(7).normal(size=(n_b, 3))
    x0 = jnp.zeros((n_i, 3))
    bad = [
        (dict(u_b=ub[:-1]), rf"u_b must have shape \({n_b}, 3\) .*got \({n_b - 1}, 3\)"),
        (dict(u_b=ub.ravel()), rf"u_b must have shape \({n_b}, 3\) .*got \({3 * n_b},\)"),
        (dict(u_b=ub[:, :2]), rf"u_b must have shape \({n_b}, 3\) .*got \({n_b}, 2\)"),
        (dict(u_i0=jnp.zeros((n_i + 1, 3))), rf"u_i0 must have shape \({n_i}, 3\) .*got \({n_i + 1}, 3\)"),
        (dict(lam_e=lam[:-1]), rf"lam_e must have shape \({n_e},\) .*got \({n_e - 1},\)"),
        (dict(mu_e=1.0), rf"mu_e must have shape \({n_e},\) .*got \(\)"),
    ]
    for change, match in bad:
        kw = {"lam_e": lam, "mu_e": mu, "u_b": ub, "u_i0": x0, **change}
        with pytest.raises(ValueError, match=match):
            solve_interior(op, kw["lam_e"], kw["mu_e"], kw["u_b"], kw["u_i0"])
    with pytest.raises(ValueError, match=rf"u_b must have shape \({n_b}, 3\)"):
        jax.jit(lambda u: solve_interior(op, lam, mu, u, x0))(ub[:-1])
    b_ii, b_ib = op.blocks(lam, mu)
    with pytest.raises(ValueError, match="b_ib must be a tuple of one array per slice"):
        solve_interior_blocks(op, b_ii, b_ii, ub, x0)
    with pytest.raises(ValueError, match=rf"n_boundary must be {n_b} .*got {n_b + 1}"):
        interior_map(op, lam, mu, n_b + 1)
    with pytest.raises(ValueError, match=r"x0 must have shape \(4,\) .*got \(3,\)"):
        pcg(lambda x: x, jnp.ones(4), jnp.zeros(3), lambda r: r)
    # batched u_b under vmap: the checks see (n_b, 3)
    batch = jnp.stack([ub, 2 * ub])
    out = jax.eval_shape(jax.vmap(lambda u: solve_interior(op, lam, mu, u, x0)[0]), batch)
    assert out.shape == (2, n_i, 3)

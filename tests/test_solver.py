"""Interior CG solve against SciPy's direct solver, warm starts, implicit gradients."""

from functools import partial

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.sparse.linalg as spla

from bayesreg import fem, stiffness
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
    from conftest import box_mesh

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
    """``u_b = 0`` (the identity deformation) makes ``b = 0``: the solution is 0 whatever
    the warm start (before: a tolerance of 0 from a non-zero warm start, NaN iterates after
    about 160 iterations, and a valid position at ``-inf``)."""
    from conftest import box_mesh

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
    from conftest import box_mesh

    from bayesreg.preconditioners import dense_preconditioner
    from bayesreg.solver import solve_interior_blocks

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


def test_dense_preconditioner_solves_to_the_direct_solution_in_few_iterations(brain):
    """``K_ii^-1`` at reference parameters (float32) preconditions solves at other parameters:
    the CG meets the same tolerance (SciPy direct solve), in a few iterations at parameters
    near the reference and in fewer than block Jacobi's far from it (the preconditioned
    eigenvalues lie between the smallest and largest ratio of the parameters)."""
    from bayesreg.preconditioners import dense_preconditioner
    from bayesreg.solver import solve_interior_blocks

    _, _, mesh = brain
    op, _ = stiffness.build_operator(mesh.nodes, mesh.tets, mesh.boundary)
    ub = np.random.default_rng(4).normal(size=(len(mesh.boundary), 3))

    def params(lam_g, mu_g):
        return np.asarray(lam_g)[mesh.tissue], np.asarray(mu_g)[mesh.tissue]

    ref = dense_preconditioner(op, op.blocks(*params([1.0, 10.0, 30.0], [1.0, 1.0, 1.0]))[0])
    assert not bool(ref.fallback) and ref.inverse.dtype == jnp.float32
    solve = jax.jit(lambda lam, mu, pre: solve_interior_blocks(
        op, *op.blocks(lam, mu), ub, jnp.zeros((op.n_interior, 3)), rtol=1e-10, maxiter=3000, precond=pre))
    for lam_g, mu_g, most in (([1.0, 10.0, 30.0], [1.0, 1.0, 1.0], 4),     # at the reference
                              ([1.1, 10.5, 29.0], [0.9, 1.0, 1.05], 8),    # a few % off
                              ([0.01, 40.0, 100.0], [0.01, 1.0, 0.5], 60)):  # far off
        lam, mu = params(lam_g, mu_g)
        u_i, info = solve(lam, mu, ref)
        _, jacobi = solve(lam, mu, None)
        assert bool(info.converged) and bool(jacobi.converged)
        expect = _reference(mesh, lam, mu, ub)
        assert np.linalg.norm(np.asarray(u_i) - expect) / np.linalg.norm(expect) < 1e-8
        assert int(info.iterations) <= most < int(jacobi.iterations)


def test_dense_preconditioner_falls_back_to_block_jacobi_when_the_factorisation_fails():
    from conftest import box_mesh

    from bayesreg.preconditioners import dense_preconditioner
    from bayesreg.solver import solve_interior_blocks

    m = box_mesh((3, 3, 3))
    op, _ = stiffness.build_operator(m.nodes, m.tets, m.boundary)
    lam, mu = np.full(len(m.tets), 10.0), np.ones(len(m.tets))
    ub = jnp.asarray(np.random.default_rng(5).normal(size=(len(m.boundary), 3)))
    x0 = jnp.zeros((op.n_interior, 3))
    u_bj, info_bj = solve_interior_blocks(op, *op.blocks(lam, mu), ub, x0)
    # an indefinite K_ii cannot be factorised: the preconditioner says so and is a Jacobi
    # inverse (of |diag K_ii|: the blocks are indefinite too), with which the solve converges
    bad = dense_preconditioner(op, op.blocks(lam, -mu)[0])
    assert bool(bad.fallback) and np.all(np.isfinite(np.asarray(bad.inverse)))
    assert np.all(np.linalg.eigvalsh(np.asarray(bad.matrix(3 * op.n_interior), np.float64)) > 0)
    u_bad, info_bad = solve_interior_blocks(op, *op.blocks(lam, mu), ub, x0, precond=bad)
    assert bool(info_bad.converged)
    np.testing.assert_allclose(np.asarray(u_bad), np.asarray(u_bj), rtol=1e-6, atol=1e-7)


def test_packed_preconditioner_is_the_dense_inverse(brain):
    """The packed lower block triangle (the CPU's storage) holds the same inverse: unpacked
    it is the dense one (whose blocks above the diagonal equal the transposes of those
    below to float32 round-off) and packs back bit for bit; its product agrees with the
    dense product to float32 round-off for block sizes that divide the DOFs or leave
    padding; a solve takes the same iterations to the same solution with either."""
    from bayesreg.preconditioners import (PACKED_BLOCK_ROWS, DensePreconditioner, dense_preconditioner,
                                          pack_symmetric, unpack_symmetric)
    from bayesreg.solver import solve_interior_blocks

    _, _, mesh = brain
    op, _ = stiffness.build_operator(mesh.nodes, mesh.tets, mesh.boundary)
    lam, mu = np.asarray([1.0, 10.0, 30.0])[mesh.tissue], np.ones(len(mesh.tets))
    n = 3 * op.n_interior
    dense = dense_preconditioner(op, op.blocks(lam, mu)[0], block_rows=1)
    packed = dense_preconditioner(op, op.blocks(lam, mu)[0])
    assert dense.inverse.shape == (n, n)
    assert packed.inverse.shape[0] == PACKED_BLOCK_ROWS * (PACKED_BLOCK_ROWS + 1) // 2
    full = np.asarray(packed.matrix(n))
    np.testing.assert_allclose(full, np.asarray(dense.inverse), rtol=0, atol=1e-6 * np.abs(full).max())
    np.testing.assert_array_equal(np.asarray(pack_symmetric(jnp.asarray(full), PACKED_BLOCK_ROWS)),
                                  np.asarray(packed.inverse))
    r = jnp.asarray(np.random.default_rng(6).normal(size=(op.n_interior, 3)))
    ref = np.asarray(dense.inverse, np.float64) @ np.asarray(r).reshape(-1)
    for rows in (1, 2, 3, 7, n // 3):  # n // 3 rows of 3: no padding
        pre = DensePreconditioner(pack_symmetric(dense.inverse, rows) if rows > 1 else dense.inverse,
                                  dense.fallback)
        got = np.asarray(jax.jit(pre.apply)(r)).reshape(-1)
        assert got.dtype == np.float64
        np.testing.assert_allclose(got, ref, rtol=0, atol=1e-5 * np.abs(ref).max())
        if rows > 1:
            np.testing.assert_array_equal(np.asarray(pack_symmetric(unpack_symmetric(pre.inverse, n), rows)),
                                          np.asarray(pre.inverse))
    ub = jnp.asarray(np.random.default_rng(7).normal(size=(len(mesh.boundary), 3)))
    lam2 = np.asarray([1.1, 10.5, 29.0])[mesh.tissue]
    solve = jax.jit(lambda pre: solve_interior_blocks(op, *op.blocks(lam2, mu), ub, jnp.zeros((op.n_interior, 3)),
                                                      rtol=1e-10, precond=pre))
    (u_d, i_d), (u_p, i_p) = solve(dense), solve(packed)
    assert bool(i_d.converged) and bool(i_p.converged)
    assert abs(int(i_d.iterations) - int(i_p.iterations)) <= 1
    np.testing.assert_allclose(np.asarray(u_p), np.asarray(u_d), rtol=1e-8, atol=1e-9 * np.abs(np.asarray(u_d)).max())


def test_a_failing_preconditioned_solve_hands_over_to_block_jacobi():
    """A preconditioner that is no approximation of ``K_ii^-1`` (indefinite) does not turn
    into rejected proposals: after ``DENSE_MAX_ITERATIONS`` the solve continues with block
    Jacobi from its iterate, to the same tolerance."""
    from conftest import box_mesh

    from bayesreg.preconditioners import DENSE_MAX_ITERATIONS, DensePreconditioner
    from bayesreg.solver import solve_interior_blocks

    m = box_mesh((3, 3, 3))
    op, _ = stiffness.build_operator(m.nodes, m.tets, m.boundary)
    lam, mu = np.full(len(m.tets), 10.0), np.ones(len(m.tets))
    ub = jnp.asarray(np.random.default_rng(8).normal(size=(len(m.boundary), 3)))
    x0 = jnp.zeros((op.n_interior, 3))
    q = np.linalg.qr(np.random.default_rng(9).normal(size=(3 * op.n_interior,) * 2))[0]
    wrong = DensePreconditioner(jnp.asarray(q @ np.diag(np.linspace(-1, 1, len(q))) @ q.T, jnp.float32),
                                jnp.asarray(False))
    u, info = solve_interior_blocks(op, *op.blocks(lam, mu), ub, x0, rtol=1e-10, precond=wrong)
    expect = _reference(m, lam, mu, np.asarray(ub))
    assert bool(info.converged) and int(info.iterations) > DENSE_MAX_ITERATIONS
    assert np.linalg.norm(np.asarray(u) - expect) / np.linalg.norm(expect) < 1e-8


def test_spectral_preconditioner_is_the_exact_inverse_at_every_lam_and_mu(brain):
    """One parameter group (``K_ii = lam A + mu B``): the generalised eigenvectors of the
    unit blocks precondition every ``lam, mu`` exactly up to float32, so a solve from zeros
    meets the direct solution at rtol 1e-10 within 2 iterations, for ratios ``lam / mu``
    from 0.1 to 10^4 (block Jacobi needs tens to hundreds); it carries no gradient and a
    gradient through the solve still matches finite differences."""
    from bayesreg.preconditioners import spectral_preconditioner
    from bayesreg.solver import solve_interior_blocks

    _, _, mesh = brain
    op, _ = stiffness.build_operator(mesh.nodes, mesh.tets, mesh.boundary)
    one = np.ones(len(mesh.tets))
    gb = stiffness.group_blocks(op, np.zeros(len(mesh.tets), int), 1)
    spec = spectral_preconditioner(op, *gb.group(0))
    assert spec.basis.dtype == jnp.float32 and float(jnp.min(spec.eigenvalues)) >= 0.0
    ub = np.random.default_rng(6).normal(size=(len(mesh.boundary), 3))
    x0 = jnp.zeros((op.n_interior, 3))

    @partial(jax.jit, static_argnames="spectral")
    def solve(lam, mu, ub, spectral=True):
        pre = spec._replace(lam=lam, mu=mu) if spectral else None
        return solve_interior_blocks(op, *op.blocks(lam * one, mu * one), ub, x0, rtol=1e-10,
                                     maxiter=5000, precond=pre)

    for lam, mu in ((0.1, 1.0), (15.0, 1.0), (30.0, 0.3), (1e4, 1.0)):
        u_i, info = solve(lam, mu, ub)
        _, jacobi = solve(lam, mu, ub, spectral=False)
        expect = _reference(mesh, lam * one, mu * one, ub)
        assert bool(info.converged) and int(info.iterations) <= 2 < int(jacobi.iterations)
        assert np.linalg.norm(np.asarray(u_i) - expect) / np.linalg.norm(expect) < 1e-9
    f = jax.jit(lambda lam: jnp.sum(solve(lam, 1.0, ub)[0] ** 2))
    g = jax.grad(f)(15.0)
    fd = (f(15.0 + 1e-4) - f(15.0 - 1e-4)) / 2e-4
    assert float(g) == pytest.approx(float(fd), rel=1e-5)
    with pytest.raises(ValueError, match="positive definite"):
        spectral_preconditioner(op, gb.group(0)[0], tuple(0.0 * b for b in gb.group(0)[1]))


def test_solver_entry_points_check_shapes_statically():
    """A u_b one node short was solved; other wrong shapes gave opaque JAX errors.  The
    checks are on shapes only: under jit they raise at tracing, under vmap they see one
    chain's shapes (a batch of valid u_b solves)."""
    from conftest import box_mesh

    from bayesreg.solver import interior_map, pcg, solve_interior_blocks

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

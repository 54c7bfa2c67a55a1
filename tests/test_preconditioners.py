"""Preconditioners of the interior solve (bayesreg.fem.preconditioners): the dense inverse at
reference parameters, its packed storage, and the exact spectral one of a uniform model."""

from functools import partial

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from bayesreg.fem import stiffness
from bayesreg.fem.preconditioners import (PACKED_BLOCK_ROWS, DensePreconditioner, dense_preconditioner,
                                      pack_symmetric, spectral_preconditioner, unpack_symmetric)
from bayesreg.fem.solver import solve_interior_blocks
from conftest import box_mesh
from helpers import direct_interior_solve


def test_dense_preconditioner_solves_to_the_direct_solution_in_few_iterations(brain):
    """``K_ii^-1`` at reference parameters (float32) preconditions solves at other parameters:
    the CG meets the same tolerance (SciPy direct solve), in a few iterations at parameters
    near the reference and in fewer than block Jacobi's far from it (the preconditioned
    eigenvalues lie between the smallest and largest ratio of the parameters)."""
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
        expect = direct_interior_solve(mesh, lam, mu, ub)
        assert np.linalg.norm(np.asarray(u_i) - expect) / np.linalg.norm(expect) < 1e-8
        assert int(info.iterations) <= most < int(jacobi.iterations)


def test_dense_preconditioner_falls_back_to_block_jacobi_when_the_factorisation_fails():

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


def test_spectral_preconditioner_is_the_exact_inverse_at_every_lam_and_mu(brain):
    """One parameter group (``K_ii = lam A + mu B``): the generalised eigenvectors of the
    unit blocks precondition every ``lam, mu`` exactly up to float32, so a solve from zeros
    meets the direct solution at rtol 1e-10 within 2 iterations, for ratios ``lam / mu``
    from 0.1 to 10^4 (block Jacobi needs tens to hundreds); it carries no gradient and a
    gradient through the solve still matches finite differences."""
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
        expect = direct_interior_solve(mesh, lam * one, mu * one, ub)
        assert bool(info.converged) and int(info.iterations) <= 2 < int(jacobi.iterations)
        assert np.linalg.norm(np.asarray(u_i) - expect) / np.linalg.norm(expect) < 1e-9
    f = jax.jit(lambda lam: jnp.sum(solve(lam, 1.0, ub)[0] ** 2))
    g = jax.grad(f)(15.0)
    fd = (f(15.0 + 1e-4) - f(15.0 - 1e-4)) / 2e-4
    assert float(g) == pytest.approx(float(fd), rel=1e-5)
    with pytest.raises(ValueError, match="positive definite"):
        spectral_preconditioner(op, gb.group(0)[0], tuple(0.0 * b for b in gb.group(0)[1]))

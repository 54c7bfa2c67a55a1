"""Interior FE solve ``K_ii u_i = -K_ib u_b`` (paper Eq. 7 with Dirichlet boundary nodes).

A jitted, float64, block-Jacobi preconditioned conjugate gradient (Hestenes-Stiefel with a
3x3 block-diagonal preconditioner), wrapped in :func:`jax.lax.custom_linear_solve` so that
``jax.grad`` differentiates implicitly through the solve (one transposed solve, no unrolled
iterations).  The solve is never silently accepted: :class:`SolveInfo` carries the
iteration count, the relative residual and a ``converged`` flag which the log-density turns
into an explicit rejection (see :mod:`bayesreg.posterior`).
"""

from __future__ import annotations

from typing import NamedTuple

from bayesreg import _xla

_xla.configure()
import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402

from bayesreg.fem import ElasticOperator, ell_matvec  # noqa: E402

__all__ = [
    "SolveInfo",
    "pcg",
    "solve_interior",
    "solve_interior_blocks",
    "interior_map",
    "interior_map_blocks",
]


class SolveInfo(NamedTuple):
    """Diagnostics of one CG solve.

    Attributes
    ----------
    iterations : int array
        CG iterations taken.
    residual : float array
        Final ``||b - A x|| / ||b||`` (0 when ``b = 0``).
    converged : bool array
        ``residual <= rtol`` within ``maxiter`` iterations.
    """

    iterations: jax.Array
    residual: jax.Array
    converged: jax.Array


def pcg(matvec, b, x0, precond, *, rtol=1e-8, maxiter=1000):
    """Preconditioned conjugate gradient for SPD ``A``.

    Parameters
    ----------
    matvec : callable
        ``x -> A x`` on arrays shaped like ``b``.
    b : array
        Right-hand side.
    x0 : array
        Initial guess (warm start), same shape as ``b``.
    precond : callable
        ``r -> M^{-1} r`` with ``M`` SPD.
    rtol : float
        Stop when ``||r|| <= rtol ||b||``.
    maxiter : int
        Iteration cap; reaching it leaves ``converged = False``.

    Returns
    -------
    x : array
    info : SolveInfo
    """
    bnorm = jnp.sqrt(jnp.vdot(b, b))
    tol2 = (rtol * bnorm) ** 2
    r0 = b - matvec(x0)
    z0 = precond(r0)
    rz0 = jnp.vdot(r0, z0)

    def cond(c):
        _, r, _, _, k = c
        return (jnp.vdot(r, r) > tol2) & (k < maxiter)

    def body(c):
        x, r, p, rz, k = c
        ap = matvec(p)
        alpha = rz / jnp.vdot(p, ap)
        x = x + alpha * p
        r = r - alpha * ap
        z = precond(r)
        rz_new = jnp.vdot(r, z)
        p = z + (rz_new / rz) * p
        return x, r, p, rz_new, k + 1

    x, r, _, _, k = jax.lax.while_loop(cond, body, (x0, r0, z0, rz0, jnp.asarray(0)))
    rnorm = jnp.sqrt(jnp.vdot(r, r))
    rel = jnp.where(bnorm > 0, rnorm / jnp.where(bnorm > 0, bnorm, 1.0), 0.0)
    # a non-finite iterate (indefinite K from invalid parameters) is not convergence
    ok = (rnorm <= rtol * bnorm) & jnp.all(jnp.isfinite(x))
    return x, SolveInfo(k, rel, ok)


def solve_interior(op: ElasticOperator, lam_e, mu_e, u_b, u_i0, *, rtol=1e-8, maxiter=1000):
    """Interior displacements from boundary displacements: ``K_ii u_i = -K_ib u_b``.

    Parameters
    ----------
    op : ElasticOperator
        Layout from :func:`bayesreg.fem.build_operator`.
    lam_e, mu_e : (M,) array
        Per-element Lamé parameters (must be positive: ``K_ii`` is then SPD).
    u_b : (n_b, 3) array
        Boundary displacements, mm.
    u_i0 : (n_i, 3) array
        Warm start (e.g. the chain's previous interior solution).
    rtol, maxiter
        See :func:`pcg`.

    Returns
    -------
    u_i : (n_i, 3) array
        Interior displacements, mm.  Differentiable in ``u_b``, ``lam_e``, ``mu_e``
        (implicit differentiation; the warm start carries no gradient).
    info : SolveInfo

    See Also
    --------
    solve_interior_blocks : the same from assembled blocks (e.g. per-group,
        :class:`bayesreg.fem.GroupBlocks`).
    """
    b_ii, b_ib = op.blocks(lam_e, mu_e)
    return solve_interior_blocks(op, b_ii, b_ib, u_b, u_i0, rtol=rtol, maxiter=maxiter)


def solve_interior_blocks(op: ElasticOperator, b_ii, b_ib, u_b, u_i0, *, rtol=1e-8, maxiter=1000):
    """:func:`solve_interior` with ``K_ii``, ``K_ib`` given as ELL blocks.

    Parameters
    ----------
    op : ElasticOperator
        Supplies the column layout (``cols_ii``, ``cols_ib``, ``self_slot``).
    b_ii : (n_i, S_i, 3, 3) array
    b_ib : (n_i, S_b, 3, 3) array
        From :meth:`bayesreg.fem.ElasticOperator.blocks` or
        :meth:`bayesreg.fem.GroupBlocks.combine`.
    u_b, u_i0, rtol, maxiter
        As :func:`solve_interior`.

    Returns
    -------
    u_i : (n_i, 3) array
        Differentiable in ``u_b`` and the blocks.
    info : SolveInfo
    """
    rhs = -ell_matvec(b_ib, op.cols_ib, u_b)
    diag = b_ii[jnp.arange(b_ii.shape[0]), op.self_slot]  # (n_i, 3, 3)
    dinv = jnp.linalg.inv(diag)
    u_i0 = jax.lax.stop_gradient(u_i0)

    def matvec(x):
        return ell_matvec(b_ii, op.cols_ii, x)

    def precond(r):
        return jnp.einsum("rij,rj->ri", dinv, r)

    def solve(mv, rhs_):
        return pcg(mv, rhs_, u_i0, precond, rtol=rtol, maxiter=maxiter)

    # K_ii is symmetric: the adjoint (gradient) solve reuses ``solve``; its warm start is
    # only an initial guess there, the tolerance is the same.
    u_i, info = jax.lax.custom_linear_solve(matvec, rhs, solve, symmetric=True, has_aux=True)
    return u_i, jax.lax.stop_gradient(info)


def _dense(blocks, cols, n_cols):
    """Dense ``(3R, 3 n_cols)`` matrix of ELL 3x3 blocks (padding column ``n_cols`` dropped)."""
    r, s_ = cols.shape
    dense = jnp.zeros((r, n_cols + 1, 3, 3), blocks.dtype)
    dense = dense.at[jnp.arange(r)[:, None], cols].add(blocks)[:, :n_cols]
    return dense.transpose(0, 2, 1, 3).reshape(3 * r, 3 * n_cols)


def interior_map(op: ElasticOperator, lam_e, mu_e, n_boundary: int):
    """Dense interior map ``H = -K_ii^{-1} K_ib``, ``(3 n_i, 3 n_b)``: ``u_i = H u_b``.

    The condensation of the FE system (paper Eq. 7) for fixed ``lam``, ``mu``: with it a
    move of the boundary nodes costs one mat-vec instead of a CG solve.  Built by a dense
    float64 Cholesky factorisation of ``K_ii`` (``O(n_i^3)``: about 0.1 s at the paper's
    mesh size on a 2-core CPU) and memory ``72 n_i n_b`` bytes; meant for meshes up to a
    few thousand nodes.  DOF order node-major on both sides (``3 * node + axis``).

    Parameters
    ----------
    op : ElasticOperator
    lam_e, mu_e : (M,) array  positive per-element Lamé parameters
    n_boundary : int  number of boundary nodes ``n_b``

    Returns
    -------
    H : (3 n_i, 3 n_b) array
        All NaN if ``K_ii`` is not numerically positive definite (the caller must treat
        that as a failed solve).
    """
    b_ii, b_ib = op.blocks(lam_e, mu_e)
    return interior_map_blocks(op, b_ii, b_ib, n_boundary)


def interior_map_blocks(op: ElasticOperator, b_ii, b_ib, n_boundary: int):
    """:func:`interior_map` with ``K_ii``, ``K_ib`` given as ELL blocks (shapes as in
    :func:`solve_interior_blocks`); returns ``H`` ``(3 n_i, 3 n_b)``, all NaN on a failed
    factorisation."""
    k_ii = _dense(b_ii, op.cols_ii, op.n_interior)
    k_ib = _dense(b_ib, op.cols_ib, n_boundary)
    chol = jnp.linalg.cholesky(0.5 * (k_ii + k_ii.T))
    return -jax.scipy.linalg.cho_solve((chol, True), k_ib)

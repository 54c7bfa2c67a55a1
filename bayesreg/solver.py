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

__all__ = ["SolveInfo", "pcg", "solve_interior"]


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
    """
    b_ii, b_ib = op.blocks(lam_e, mu_e)
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

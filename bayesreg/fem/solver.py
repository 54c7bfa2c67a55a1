"""Interior FE solve ``K_ii u_i = -K_ib u_b`` (paper Eq. 7 with Dirichlet boundary nodes).

A jitted, float64 preconditioned conjugate gradient (Hestenes-Stiefel), wrapped in
:func:`jax.lax.custom_linear_solve` so that ``jax.grad`` differentiates implicitly through
the solve (one transposed solve, no unrolled iterations).  The preconditioner is 3x3 block
Jacobi by default, or one of :mod:`bayesreg.fem.preconditioners` (a dense ``K_ii^-1`` at nearby
parameters, or the exact spectral one of a one-group model).  :func:`interior_map` gives
the dense map ``H`` with ``u_i = H u_b`` (one Cholesky factorisation) for moves of ``u_b``
alone.

The solve is never silently accepted: :class:`SolveInfo` carries the iteration count, the
relative residual and a ``converged`` flag which the log-density turns into an explicit
rejection (see :mod:`bayesreg.model.posterior`).  The tolerance does not depend on the
preconditioner: it changes the iterations, not the solution.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from bayesreg._checks import check_shape
from bayesreg.fem.preconditioners import DENSE_MAX_ITERATIONS, DensePreconditioner
from bayesreg.fem.stiffness import ElasticOperator, check_blocks, ell_dense, ell_diagonal, ell_matvec

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


def _check_displacements(op: ElasticOperator, u_b, u_i0):
    """``u_b`` ``(n_b, 3)`` (``n_b`` known where ``op`` holds its boundary) and ``u_i0``
    ``(n_i, 3)``."""
    n_b = op.n_boundary
    shape = jnp.shape(u_b)
    if len(shape) != 2 or shape[1] != 3 or (n_b is not None and shape[0] != n_b):
        expected = f"({n_b}, 3)" if n_b is not None else "(n_b, 3)"
        raise ValueError(f"u_b must have shape {expected} (boundary displacements, one row per "
                         f"boundary node), got {shape}")
    check_shape("u_i0", u_i0, (op.n_interior, 3), "warm start, one row per interior node")


def pcg(matvec, b, x0, precond, *, rtol=1e-8, maxiter=1000):
    """Preconditioned conjugate gradient for SPD ``A``.

    Parameters
    ----------
    matvec : callable
        ``x -> A x`` on arrays shaped like ``b``.
    b : array
        Right-hand side.
    x0 : array
        Initial guess (warm start), same shape as ``b``; ignored when ``b = 0`` (the
        solution is then 0, in 0 iterations).
    precond : callable
        ``r -> M^{-1} r`` with ``M`` SPD.
    rtol : float
        Stop when ``||r|| <= rtol ||b||``.
    maxiter : int or int array
        Iteration cap; reaching it leaves ``converged = False``.

    Returns
    -------
    x : array
    info : SolveInfo

    Raises
    ------
    ValueError
        ``x0`` not of the shape of ``b``.
    """
    check_shape("x0", x0, jnp.shape(b), "the shape of b")
    bnorm = jnp.sqrt(jnp.vdot(b, b))
    tol2 = (rtol * bnorm) ** 2
    # b = 0 (u_b = 0: the identity deformation): the solution is 0, and a residual tolerance
    # of 0 would never be met from a non-zero warm start (the iterates end in 0/0)
    x0 = jnp.where(bnorm > 0, x0, jnp.zeros_like(x0))
    r0 = b - matvec(x0)

    def cond(c):
        _, r, _, _, k = c
        return (jnp.vdot(r, r) > tol2) & (k < maxiter)

    def body(c):
        # the preconditioner is applied at the top of an iteration, so a residual that
        # meets the tolerance is never preconditioned (one dense product saved per solve)
        x, r, p, rz_old, k = c
        z = precond(r)
        rz = jnp.vdot(r, z)
        p = z + jnp.where(k > 0, rz / rz_old, 0.0) * p
        ap = matvec(p)
        alpha = rz / jnp.vdot(p, ap)
        return x + alpha * p, r - alpha * ap, p, rz, k + 1

    init = (x0, r0, jnp.zeros_like(b), jnp.ones((), b.dtype), jnp.asarray(0))
    x, r, _, _, k = jax.lax.while_loop(cond, body, init)
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
        Layout from :func:`bayesreg.fem.stiffness.build_operator`.
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

    Raises
    ------
    ValueError
        ``lam_e`` or ``mu_e`` not of shape ``(M,)``, ``u_b`` not ``(n_b, 3)`` or ``u_i0`` not
        ``(n_i, 3)`` (static shape checks, valid under ``jit`` and ``vmap``; the values are
        not checked: non-positive parameters give a solve reported not converged).

    Examples
    --------
    A rigid translation of the boundary moves the interior with it (``K`` annihilates rigid
    motions), here the centre of a cube of 12 tetrahedra:

    >>> import jax.numpy as jnp, numpy as np
    >>> import bayesreg
    >>> from bayesreg.mesh.tetmesh import boundary_nodes, orient_tets
    >>> from bayesreg.fem.solver import solve_interior
    >>> from bayesreg.fem.stiffness import build_operator
    >>> bayesreg.configure_jax()
    >>> corners = np.array([[x, y, z] for x in (0.0, 20.0) for y in (0.0, 20.0) for z in (0.0, 20.0)])
    >>> nodes = np.vstack([corners, [[10.0, 10.0, 10.0]]])
    >>> faces = [(0, 1, 3, 2), (4, 5, 7, 6), (0, 1, 5, 4), (2, 3, 7, 6), (0, 2, 6, 4), (1, 3, 7, 5)]
    >>> tets = orient_tets(nodes, np.array([t for a, b, c, d in faces for t in ([a, b, c, 8], [a, c, d, 8])]))
    >>> op, interior = build_operator(nodes, tets, boundary_nodes(tets))
    >>> u_b = jnp.tile(jnp.array([1.0, -2.0, 0.5]), (8, 1))  # mm
    >>> u_i, info = solve_interior(op, jnp.full(12, 10.0), jnp.ones(12), u_b, jnp.zeros((1, 3)))
    >>> np.round(np.asarray(u_i), 6).tolist(), bool(info.converged)
    ([[1.0, -2.0, 0.5]], True)

    See Also
    --------
    solve_interior_blocks : the same from assembled blocks (e.g. per-group,
        :class:`bayesreg.fem.stiffness.GroupBlocks`).
    """
    _check_displacements(op, u_b, u_i0)
    b_ii, b_ib = op.blocks(lam_e, mu_e)
    return solve_interior_blocks(op, b_ii, b_ib, u_b, u_i0, rtol=rtol, maxiter=maxiter)


def solve_interior_blocks(op: ElasticOperator, b_ii, b_ib, u_b, u_i0, *, rtol=1e-8, maxiter=1000,
                          precond: DensePreconditioner | None = None):
    """:func:`solve_interior` with ``K_ii``, ``K_ib`` given as ELL blocks.

    Parameters
    ----------
    op : ElasticOperator
        Supplies the sliced ELL layout (``cols_ii``, ``row_ii``, ``cols_ib``, ``row_ib``).
    b_ii, b_ib : tuples of (R_k, S_k, 3, 3) arrays
        Sliced ELL blocks of ``K_ii``, ``K_ib``, from :meth:`bayesreg.fem.stiffness.ElasticOperator.blocks` or
        :meth:`bayesreg.fem.stiffness.GroupBlocks.combine`.
    u_b, u_i0, rtol, maxiter
        As :func:`solve_interior`.
    precond : DensePreconditioner or SpectralPreconditioner, optional
        Preconditioner (built at any positive parameters, :func:`bayesreg.fem.preconditioners.dense_preconditioner`, or
        exact at the current ones, :func:`bayesreg.fem.preconditioners.spectral_preconditioner`); default the 3x3 block
        Jacobi of ``b_ii``.  It carries no gradient.  A
        preconditioned solve that has not converged after ``min(maxiter,
        DENSE_MAX_ITERATIONS)`` iterations (a preconditioner built too far from the current
        parameters, or a float32 factor spoilt by the conditioning) continues from its
        iterate with block Jacobi for up to ``maxiter`` more; ``info`` counts both.

    Returns
    -------
    u_i : (n_i, 3) array
        Differentiable in ``u_b`` and the blocks.
    info : SolveInfo

    Raises
    ------
    ValueError
        ``b_ii``, ``b_ib`` not of ``op``'s layout, ``u_b`` not ``(n_b, 3)`` or ``u_i0`` not
        ``(n_i, 3)`` (static shape checks).
    """
    check_blocks("b_ii", b_ii, op.cols_ii)
    check_blocks("b_ib", b_ib, op.cols_ib)
    _check_displacements(op, u_b, u_i0)
    rhs = -ell_matvec(b_ib, op.cols_ib, op.row_ib, u_b)
    u_i0 = jax.lax.stop_gradient(u_i0)

    def matvec(x):
        return ell_matvec(b_ii, op.cols_ii, op.row_ii, x)

    def jacobi():
        dinv = jnp.linalg.inv(ell_diagonal(b_ii, op.row_ii))  # (n_i, 3, 3)
        return lambda r: jnp.einsum("rij,rj->ri", dinv, r)

    def solve(mv, rhs_):
        if precond is None:
            return pcg(mv, rhs_, u_i0, jacobi(), rtol=rtol, maxiter=maxiter)
        x, info = pcg(mv, rhs_, u_i0, jax.lax.stop_gradient(precond).apply, rtol=rtol,
                      maxiter=jnp.minimum(maxiter, DENSE_MAX_ITERATIONS))

        def rescue(_):
            start = jnp.where(jnp.all(jnp.isfinite(x)), x, u_i0)
            y, more = pcg(mv, rhs_, start, jacobi(), rtol=rtol, maxiter=maxiter)
            return y, SolveInfo(info.iterations + more.iterations, more.residual, more.converged)

        return jax.lax.cond(info.converged, lambda _: (x, info), rescue, None)

    # K_ii is symmetric: the adjoint (gradient) solve reuses ``solve``; its warm start is
    # only an initial guess there, the tolerance is the same.
    u_i, info = jax.lax.custom_linear_solve(matvec, rhs, solve, symmetric=True, has_aux=True)
    return u_i, jax.lax.stop_gradient(info)


def interior_map(op: ElasticOperator, lam_e, mu_e, n_boundary: int):
    """Dense interior map ``H = -K_ii^{-1} K_ib``, ``(3 n_i, 3 n_b)``: ``u_i = H u_b``.

    The condensation of the FE system (paper Eq. 7) for fixed ``lam``, ``mu``: with it a
    move of the boundary nodes costs one mat-vec instead of a CG solve.  Built by a dense
    float64 Cholesky factorisation of ``K_ii`` (``O(n_i^3)`` flops) and memory ``72 n_i n_b``
    bytes; meant for meshes up to a
    few thousand nodes.  DOF order node-major on both sides (``3 * node + axis``).

    Parameters
    ----------
    op : ElasticOperator
    lam_e, mu_e : (M,) array
        positive per-element Lamé parameters
    n_boundary : int
        number of boundary nodes ``n_b``

    Returns
    -------
    H : (3 n_i, 3 n_b) array
        All NaN if ``K_ii`` is not numerically positive definite (the caller must treat
        that as a failed solve).

    Raises
    ------
    ValueError
        ``lam_e`` or ``mu_e`` not of shape ``(M,)``, or ``n_boundary`` not ``op``'s ``n_b``.
    """
    b_ii, b_ib = op.blocks(lam_e, mu_e)
    return interior_map_blocks(op, b_ii, b_ib, n_boundary)


def interior_map_blocks(op: ElasticOperator, b_ii, b_ib, n_boundary: int):
    """:func:`interior_map` with ``K_ii``, ``K_ib`` given as ELL blocks (shapes as in
    :func:`solve_interior_blocks`); returns ``H`` ``(3 n_i, 3 n_b)``, all NaN on a failed
    factorisation.  Raises ``ValueError`` on blocks not of ``op``'s layout or an
    ``n_boundary`` other than ``op``'s."""
    check_blocks("b_ii", b_ii, op.cols_ii)
    check_blocks("b_ib", b_ib, op.cols_ib)
    if op.n_boundary is not None and n_boundary != op.n_boundary:
        raise ValueError(f"n_boundary must be {op.n_boundary} (op's number of boundary nodes), "
                         f"got {n_boundary}")
    k_ii = ell_dense(b_ii, op.cols_ii, op.row_ii, op.n_interior)
    k_ib = ell_dense(b_ib, op.cols_ib, op.row_ib, n_boundary)
    chol = jnp.linalg.cholesky(0.5 * (k_ii + k_ii.T))
    return -jax.scipy.linalg.cho_solve((chol, True), k_ib)

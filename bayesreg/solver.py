"""Interior FE solve ``K_ii u_i = -K_ib u_b`` (paper Eq. 7 with Dirichlet boundary nodes).

A jitted, float64 preconditioned conjugate gradient (Hestenes-Stiefel), wrapped in
:func:`jax.lax.custom_linear_solve` so that ``jax.grad`` differentiates implicitly through
the solve (one transposed solve, no unrolled iterations).  Two preconditioners:

* 3x3 block Jacobi (the default): free, but ``K_ii`` of brain tissue is ill-conditioned
  (``lam / mu`` of 10-30 and more: 60-180 iterations to a relative residual of 1e-8);
* :class:`DensePreconditioner`: the inverse of ``K_ii`` at reference parameters, in float32
  (:func:`dense_preconditioner`).  ``K_ii`` is linear in the Lamé parameters of each group,
  so with ``r_g`` the ratios of the current parameters to the reference ones the
  preconditioned matrix has its eigenvalues in ``[min_g r_g, max_g r_g]``: one preconditioner
  built at a chain's parameters serves the chain's next solves while its parameters stay
  near (measured on the paper-size mesh: 2-3 iterations a thousand random-walk steps after
  the reference, 25 with the reference a factor 100 off, against 100-180 with block Jacobi).
* :class:`SpectralPreconditioner`, for one parameter group (``K_ii = lam A + mu B``, the
  uniform model): the generalised eigenvectors of ``(A, B)`` give ``K_ii^-1`` exactly at
  every ``lam, mu`` (:func:`spectral_preconditioner`), so one float32 basis, built once and
  shared by all chains, makes every solve converge in one or two iterations.

The solve is never silently accepted: :class:`SolveInfo` carries the iteration count, the
relative residual and a ``converged`` flag which the log-density turns into an explicit
rejection (see :mod:`bayesreg.posterior`).  The tolerance does not depend on the
preconditioner: it changes the iterations, not the solution.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from bayesreg import _xla

_xla.configure()
import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402

from bayesreg.fem import ElasticOperator, ell_dense, ell_diagonal, ell_matvec  # noqa: E402

__all__ = [
    "SolveInfo",
    "DensePreconditioner",
    "dense_preconditioner",
    "PACKED_BLOCK_ROWS",
    "pack_symmetric",
    "unpack_symmetric",
    "SpectralPreconditioner",
    "spectral_preconditioner",
    "DENSE_MAX_DOFS",
    "DENSE_MAX_ITERATIONS",
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


#: Iterations of a solve preconditioned by :class:`DensePreconditioner` before it hands over
#: to block Jacobi (:func:`solve_interior_blocks`): 2-3 are typical, 25 with the reference
#: parameters a factor 100 off.
DENSE_MAX_ITERATIONS = 50

#: Largest ``3 n_i`` for which :func:`dense_preconditioner` is chosen by ``auto`` (its
#: inverse takes ``4 (3 n_i)^2`` bytes per chain: 67 MB at 4096, 7.5 MB at the paper's size).
DENSE_MAX_DOFS = 4096


def _check_shape(name, value, expected, what):
    """Static check (shapes are known under ``jit``; under ``vmap`` they are those of one
    chain): ``value.shape == expected``.  Also used by :mod:`bayesreg.posterior`."""
    shape = jnp.shape(value)
    if shape != expected:
        raise ValueError(f"{name} must have shape {expected} ({what}), got {shape}")


def _check_blocks(name, blocks, cols):
    """The ELL blocks ``name`` match the sliced layout of ``cols`` (``op.cols_ii`` or
    ``op.cols_ib``): one ``(R_k, S_k, 3, 3)`` array per slice."""
    expected = [tuple(c.shape) + (3, 3) for c in cols]
    got = ([jnp.shape(b) for b in blocks] if isinstance(blocks, (tuple, list))
           else type(blocks).__name__)
    if got != expected:
        raise ValueError(f"{name} must be a tuple of one array per slice of op's layout with "
                         f"shapes {expected}, got {got}")


def _check_displacements(op: ElasticOperator, u_b, u_i0):
    """``u_b`` ``(n_b, 3)`` (``n_b`` known where ``op`` holds its boundary) and ``u_i0``
    ``(n_i, 3)``."""
    n_b = op.n_boundary
    shape = jnp.shape(u_b)
    if len(shape) != 2 or shape[1] != 3 or (n_b is not None and shape[0] != n_b):
        expected = f"({n_b}, 3)" if n_b is not None else "(n_b, 3)"
        raise ValueError(f"u_b must have shape {expected} (boundary displacements, one row per "
                         f"boundary node), got {shape}")
    _check_shape("u_i0", u_i0, (op.n_interior, 3), "warm start, one row per interior node")


#: Block rows of the packed storage of :class:`DensePreconditioner` on a CPU (its lower block
#: triangle, ``R (R + 1) / 2`` blocks): 8 at the paper's size gives blocks of 185 DOFs and
#: 56% of the dense bytes.  On other backends the inverse stays dense (1: the form measured
#: on the GPUs, where the chains' batched dense products run at the device's bandwidth).
PACKED_BLOCK_ROWS = 8


def _tril_blocks(n_blocks: int) -> tuple[int, np.ndarray, np.ndarray]:
    """``R`` and the block rows and columns ``(R (R + 1) / 2,)`` of a packed lower block
    triangle of ``n_blocks`` blocks."""
    r = int(round((np.sqrt(8 * n_blocks + 1) - 1) / 2))
    if r * (r + 1) // 2 != n_blocks:
        raise ValueError(f"a packed lower block triangle has R (R + 1) / 2 blocks, got {n_blocks}")
    return (r, *np.tril_indices(r))


def pack_symmetric(matrix, block_rows: int):
    """The lower block triangle of a symmetric ``(n, n)`` matrix, ``(R (R + 1) / 2, b, b)``.

    ``b = ceil(n / R)``; the matrix is padded with zeros to ``R b``.  Blocks in row-major
    order of the triangle (``numpy.tril_indices(R)``).  The blocks above the diagonal are
    taken to be the transposes of those below (a float32 inverse ``L^-T L^-1`` is symmetric
    to round-off only).  Inverse: :func:`unpack_symmetric`.
    """
    n = matrix.shape[0]
    b = -(-n // block_rows)
    m = jnp.pad(matrix, ((0, block_rows * b - n),) * 2)
    m = m.reshape(block_rows, b, block_rows, b).transpose(0, 2, 1, 3)
    rows, cols = np.tril_indices(block_rows)
    return m[rows, cols]


def unpack_symmetric(packed, n: int):
    """The symmetric ``(n, n)`` matrix of a packed lower block triangle (:func:`pack_symmetric`)."""
    r, rows, cols = _tril_blocks(packed.shape[0])
    b = packed.shape[1]
    full = jnp.zeros((r, r, b, b), packed.dtype).at[cols, rows].set(jnp.swapaxes(packed, 1, 2))
    full = full.at[rows, cols].set(packed)  # the diagonal blocks as stored
    return full.transpose(0, 2, 1, 3).reshape(r * b, r * b)[:n, :n]


class DensePreconditioner(NamedTuple):
    """The inverse of ``K_ii`` at reference Lamé parameters, a preconditioner of the CG.

    Attributes
    ----------
    inverse : float32 array, (3 n_i, 3 n_i) or (R (R + 1) / 2, b, b)
        ``K_ii(lam_ref, mu_ref)^-1``, DOFs node-major (``3 * row + axis``, rows in the
        :class:`bayesreg.fem.ElasticOperator`'s interior order); symmetric positive
        definite.  Dense, or packed as its lower block triangle (:func:`pack_symmetric`,
        ``R`` block rows of ``b`` DOFs, zero-padded to ``R b``), which
        :func:`dense_preconditioner` builds on a CPU (:data:`PACKED_BLOCK_ROWS`).  Applied
        as one float32 product per CG iteration: dense, one matrix-vector product; packed,
        each block twice (itself and its transpose) in two batched products.
    fallback : () bool array
        The float32 factorisation failed (``K_ii`` at the reference not numerically
        positive definite) and ``inverse`` holds the 3x3 block-Jacobi inverse instead (the
        inverse of ``|diag K_ii|`` where those blocks are not positive definite either).

    Notes
    -----
    Why packed on a CPU: XLA:CPU runs the batched products on all the cores it has, the
    dense matrix-vector product on one.  At the paper's size (1,479 DOFs, 4.9 instead of
    8.75 MB) a product took 0.134 against 0.218 ms on the 2-core CPU, and one chain ran
    1.3-1.5x the MH steps/s; pinned to one core, or with a chain per core, the same as
    dense (``benchmarks/README.md``, "The preconditioner packed", 2026-11-26).  The
    preconditioned residuals agree with the dense form's to float32 round-off.
    """

    inverse: jax.Array
    fallback: jax.Array

    def apply(self, r):
        """``M^-1 r`` for ``r`` ``(n_i, 3)`` float64 (computed in float32, returned float64)."""
        x = r.reshape(-1).astype(self.inverse.dtype)
        if self.inverse.ndim == 2:
            return (self.inverse @ x).astype(r.dtype).reshape(r.shape)
        n_rows, rows, cols = _tril_blocks(self.inverse.shape[0])
        b = self.inverse.shape[1]
        x = jnp.pad(x, (0, n_rows * b - x.size)).reshape(n_rows, b)
        lower = jax.lax.dot_general(self.inverse, x[cols], (((2,), (1,)), ((0,), (0,))))
        # the transposed blocks above the diagonal (the diagonal blocks' masked out: a slice
        # of the off-diagonal ones would copy them at every product)
        upper = jax.lax.dot_general(self.inverse, x[rows], (((1,), (1,)), ((0,), (0,))))
        upper = upper * jnp.asarray(rows != cols, x.dtype)[:, None]
        y = (jax.ops.segment_sum(lower, rows, n_rows, indices_are_sorted=True)
             + jax.ops.segment_sum(upper, cols, n_rows))
        return y.reshape(-1)[:r.size].astype(r.dtype).reshape(r.shape)

    def matrix(self, n: int):
        """The inverse as a dense symmetric ``(n, n)`` float32 matrix (``n = 3 n_i``)."""
        if self.inverse.ndim == 2:
            return self.inverse
        return unpack_symmetric(self.inverse, n)


def dense_preconditioner(op: ElasticOperator, b_ii, *, block_rows: int | None = None
                         ) -> DensePreconditioner:
    """:class:`DensePreconditioner` of ``K_ii`` given as ELL blocks.

    ``K_ii`` is scaled to unit diagonal (``D^-1/2 K_ii D^-1/2``), factorised by Cholesky in
    float32 and inverted (``L^-T L^-1``), and the scaling is folded back into the inverse.
    Cost ``(3 n_i)^3`` flops: about 80 ms at the paper's size (1,371 interior DOFs) on one
    core of the 2-core CPU; memory ``4 (3 n_i)^2`` bytes (see :data:`DENSE_MAX_DOFS`).

    A preconditioner only has to be close to ``K_ii^-1``: float32 halves the bytes that each
    application streams (a 1,371-DOF product took 114 us against 243 us in float64), and the
    CG iterates in float64 to the same tolerance (float32 alone floors near 4e-7).

    Parameters
    ----------
    op : ElasticOperator
    b_ii : tuple of (R_k, S_k, 3, 3) arrays
        Sliced ELL blocks of ``K_ii`` at the reference parameters
        (:func:`bayesreg.posterior.stiffness_blocks`).
    block_rows : int, optional
        Packed storage in this many block rows (:class:`DensePreconditioner`); 1 keeps the
        inverse dense.  Default :data:`PACKED_BLOCK_ROWS` on a CPU backend, else 1.

    Returns
    -------
    DensePreconditioner
        With ``fallback`` set, and a Jacobi inverse in place (see
        :attr:`DensePreconditioner.fallback`), when the float32 factorisation fails
        (non-positive parameters, or a conditioning beyond float32).

    Raises
    ------
    ValueError
        ``b_ii`` not of ``op``'s layout (a static shape check), or ``block_rows < 1``.
    """
    _check_blocks("b_ii", b_ii, op.cols_ii)
    if block_rows is None:
        block_rows = PACKED_BLOCK_ROWS if jax.default_backend() == "cpu" else 1
    if block_rows < 1:
        raise ValueError(f"block_rows must be >= 1, got {block_rows}")
    n = 3 * op.n_interior
    k = jax.lax.stop_gradient(ell_dense(b_ii, op.cols_ii, op.row_ii, op.n_interior))
    d = 1.0 / jnp.sqrt(jnp.abs(jnp.diag(k)))
    s = (k * d[:, None] * d[None, :]).astype(jnp.float32)
    chol = jnp.linalg.cholesky(0.5 * (s + s.T))
    l_inv = jax.scipy.linalg.solve_triangular(chol, jnp.eye(n, dtype=jnp.float32), lower=True)
    d32 = d.astype(jnp.float32)
    inv = d32[:, None] * (l_inv.T @ l_inv) * d32[None, :]
    ok = jnp.all(jnp.isfinite(inv))
    # fallback: the 3x3 block Jacobi where its blocks are positive definite, else the
    # inverse of |diag K_ii| (positive definite whatever the parameters)
    diag = jax.lax.stop_gradient(ell_diagonal(b_ii, op.row_ii))  # (n_i, 3, 3)
    spd = jnp.all(jnp.isfinite(jnp.linalg.cholesky(diag)))
    point = jnp.eye(3) / jnp.maximum(jnp.abs(jnp.diagonal(diag, axis1=1, axis2=2)), 1e-300)[:, :, None]
    blocks = jnp.where(spd, jnp.linalg.inv(diag), point).astype(jnp.float32)
    rows = jnp.arange(op.n_interior)
    jacobi = jnp.zeros((op.n_interior, 3, op.n_interior, 3), jnp.float32)
    jacobi = jacobi.at[rows, :, rows, :].set(blocks).reshape(n, n)
    inverse = jnp.where(ok, inv, jacobi)
    block_rows = min(block_rows, n)
    return DensePreconditioner(inverse if block_rows == 1 else pack_symmetric(inverse, block_rows), ~ok)


class SpectralPreconditioner(NamedTuple):
    """``K_ii^-1`` of a one-group stiffness ``K_ii = lam A + mu B`` at any ``lam, mu > 0``.

    With ``A V = B V diag(w)`` and ``V^T B V = I`` (the generalised symmetric eigenproblem
    of the unit blocks: ``B``, the shear part with the boundary held, is positive definite,
    ``A``, the volumetric part, semi-definite), ``K_ii = V^-T diag(lam w + mu) V^-1``, so
    ``K_ii^-1 = V diag(1 / (lam w + mu)) V^T``: exact for every parameter value, where
    :class:`DensePreconditioner` holds one value's inverse.  ``V`` is stored in float32 (the
    CG iterates in float64 to its own tolerance; the float32 rounding leaves one or two
    iterations to do: measured 1.0 per proposal to 1e-8 from the paper's uniform config's
    starts and 1.8 after its warm-up, against 3.2-3.5 with each chain's chunk-start dense
    inverse, ``benchmarks/steps.py``) and is the same for every chain.

    Attributes
    ----------
    basis : (3 n_i, 3 n_i) float32 array
        ``V``, DOFs node-major in the :class:`bayesreg.fem.ElasticOperator`'s interior order.
    eigenvalues : (3 n_i,) float64 array
        ``w >= 0`` (round-off may leave the smallest at about ``-1e-16``).
    lam, mu : () arrays
        The parameters at which :meth:`apply` inverts ``K_ii`` (set per solve with
        ``_replace``; :func:`spectral_preconditioner` returns ``1, 1``).
    """

    basis: jax.Array
    eigenvalues: jax.Array
    lam: jax.Array
    mu: jax.Array

    def apply(self, r):
        """``K_ii(lam, mu)^-1 r`` for ``r`` ``(n_i, 3)`` float64: two float32 products."""
        t = r.reshape(-1).astype(self.basis.dtype) @ self.basis  # V^T r
        d = 1.0 / jnp.maximum(self.lam * self.eigenvalues + self.mu, 1e-300)
        z = self.basis @ (t * d.astype(self.basis.dtype))
        return z.astype(r.dtype).reshape(r.shape)


def spectral_preconditioner(op: ElasticOperator, lam_ii, mu_ii) -> SpectralPreconditioner:
    """:class:`SpectralPreconditioner` from the unit blocks of ``K_ii`` of one group.

    Host computation (SciPy's generalised ``eigh``, float64): about 1-2 s at the paper's
    size (1,400 interior DOFs) on the 2-core CPU, memory ``4 (3 n_i)^2`` bytes for the basis
    (see :data:`DENSE_MAX_DOFS`).

    Parameters
    ----------
    op : ElasticOperator
    lam_ii, mu_ii : tuples of (R_k, S_k, 3, 3) arrays
        Sliced ELL blocks of ``K_ii`` for ``lam = 1, mu = 0`` and ``lam = 0, mu = 1``
        (:meth:`bayesreg.fem.GroupBlocks.group` of a single group).

    Returns
    -------
    SpectralPreconditioner
        With ``lam = mu = 1``.

    Raises
    ------
    ValueError
        ``lam_ii`` or ``mu_ii`` not of ``op``'s layout, the shear part ``B`` not positive
        definite (no Dirichlet boundary holds the interior) or the volumetric part with a
        negative eigenvalue beyond round-off.
    """
    import scipy.linalg as sla

    _check_blocks("lam_ii", lam_ii, op.cols_ii)
    _check_blocks("mu_ii", mu_ii, op.cols_ii)

    n = op.n_interior
    a = np.asarray(ell_dense(lam_ii, op.cols_ii, op.row_ii, n), np.float64)
    b = np.asarray(ell_dense(mu_ii, op.cols_ii, op.row_ii, n), np.float64)
    try:
        w, v = sla.eigh(0.5 * (a + a.T), 0.5 * (b + b.T))
    except np.linalg.LinAlgError as exc:
        raise ValueError(f"spectral preconditioner: the shear stiffness of the interior is not "
                         f"positive definite ({exc})") from None
    if w[0] < -1e-8 * max(w[-1], 1.0):
        raise ValueError(f"spectral preconditioner: negative volumetric eigenvalue {w[0]:.3g}")
    return SpectralPreconditioner(jnp.asarray(v, jnp.float32), jnp.asarray(np.maximum(w, 0.0)),
                                  jnp.asarray(1.0), jnp.asarray(1.0))


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
    _check_shape("x0", x0, jnp.shape(b), "the shape of b")
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

    Raises
    ------
    ValueError
        ``lam_e`` or ``mu_e`` not of shape ``(M,)``, ``u_b`` not ``(n_b, 3)`` or ``u_i0`` not
        ``(n_i, 3)`` (static shape checks, valid under ``jit`` and ``vmap``; the values are
        not checked: non-positive parameters give a solve reported not converged).

    See Also
    --------
    solve_interior_blocks : the same from assembled blocks (e.g. per-group,
        :class:`bayesreg.fem.GroupBlocks`).
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
        Sliced ELL blocks of ``K_ii``, ``K_ib``, from :meth:`bayesreg.fem.ElasticOperator.blocks` or
        :meth:`bayesreg.fem.GroupBlocks.combine`.
    u_b, u_i0, rtol, maxiter
        As :func:`solve_interior`.
    precond : DensePreconditioner or SpectralPreconditioner, optional
        Preconditioner (built at any positive parameters, :func:`dense_preconditioner`, or
        exact at the current ones, :func:`spectral_preconditioner`); default the 3x3 block
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
    _check_blocks("b_ii", b_ii, op.cols_ii)
    _check_blocks("b_ib", b_ib, op.cols_ib)
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
    _check_blocks("b_ii", b_ii, op.cols_ii)
    _check_blocks("b_ib", b_ib, op.cols_ib)
    if op.n_boundary is not None and n_boundary != op.n_boundary:
        raise ValueError(f"n_boundary must be {op.n_boundary} (op's number of boundary nodes), "
                         f"got {n_boundary}")
    k_ii = ell_dense(b_ii, op.cols_ii, op.row_ii, op.n_interior)
    k_ib = ell_dense(b_ib, op.cols_ib, op.row_ib, n_boundary)
    chol = jnp.linalg.cholesky(0.5 * (k_ii + k_ii.T))
    return -jax.scipy.linalg.cho_solve((chol, True), k_ib)

"""CG preconditioners of the interior solve ``K_ii u_i = -K_ib u_b``.

* 3x3 block Jacobi (in :mod:`bayesreg.fem.solver`, the default): free, but ``K_ii`` of brain
  tissue is ill-conditioned (``lam / mu`` of 10-30 and more), so CG needs of the order of a
  hundred iterations;
* :class:`DensePreconditioner`: the inverse of ``K_ii`` at reference parameters, in float32
  (:func:`dense_preconditioner`).  ``K_ii`` is linear in the Lamé parameters of each group,
  so with ``r_g`` the ratios of the current parameters to the reference ones the
  preconditioned matrix has its eigenvalues in ``[min_g r_g, max_g r_g]``: one preconditioner
  built at a chain's parameters serves the chain's next solves while its parameters stay
  near (a few iterations instead of a hundred);
* :class:`SpectralPreconditioner`, for one parameter group (``K_ii = lam A + mu B``, the
  uniform model): the generalised eigenvectors of ``(A, B)`` give ``K_ii^-1`` exactly at
  every ``lam, mu`` (:func:`spectral_preconditioner`), so one float32 basis, built once and
  shared by all chains, makes every solve converge in one or two iterations.

A preconditioner changes the iterations a solve takes, never the tolerance it meets.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from bayesreg.fem.stiffness import ElasticOperator, check_blocks, ell_dense, ell_diagonal

__all__ = ["DensePreconditioner", "dense_preconditioner", "SpectralPreconditioner",
           "spectral_preconditioner", "pack_symmetric", "unpack_symmetric", "PACKED_BLOCK_ROWS",
           "DENSE_MAX_DOFS", "DENSE_MAX_ITERATIONS"]


#: Iterations of a solve preconditioned by :class:`DensePreconditioner` before it hands over
#: to block Jacobi (:func:`bayesreg.fem.solver.solve_interior_blocks`): a few are typical, a few
#: tens with the reference parameters a factor 100 off.
DENSE_MAX_ITERATIONS = 50


#: Largest ``3 n_i`` for which :func:`dense_preconditioner` is chosen by ``auto`` (its
#: inverse takes ``4 (3 n_i)^2`` bytes per chain: 67 MB at 4096, 7.5 MB at the paper's size).
DENSE_MAX_DOFS = 4096


#: Block rows of the packed storage of :class:`DensePreconditioner` on a CPU (its lower block
#: triangle, ``R (R + 1) / 2`` blocks): 8 at the paper's size gives blocks of 185 DOFs and
#: 56% of the dense bytes.  On other backends the inverse stays dense (1: the chains'
#: batched dense products run at the device's bandwidth).
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
        :class:`bayesreg.fem.stiffness.ElasticOperator`'s interior order); symmetric positive
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
    dense matrix-vector product on one, so a single chain with idle cores runs faster
    packed; with a chain per core the two forms cost the same.  The preconditioned
    residuals agree with the dense form's to float32 round-off.
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
    Cost ``(3 n_i)^3`` flops; memory ``4 (3 n_i)^2`` bytes (see :data:`DENSE_MAX_DOFS`).

    A preconditioner only has to be close to ``K_ii^-1``: float32 halves the bytes that each
    application streams (a 1,371-DOF product took 114 us against 243 us in float64), and the
    CG iterates in float64 to the same tolerance (float32 alone floors near 4e-7).

    Parameters
    ----------
    op : ElasticOperator
    b_ii : tuple of (R_k, S_k, 3, 3) arrays
        Sliced ELL blocks of ``K_ii`` at the reference parameters
        (:func:`bayesreg.model.posterior.stiffness_blocks`).
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
    check_blocks("b_ii", b_ii, op.cols_ii)
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
    iterations to do) and is the same for every chain.

    Attributes
    ----------
    basis : (3 n_i, 3 n_i) float32 array
        ``V``, DOFs node-major in the :class:`bayesreg.fem.stiffness.ElasticOperator`'s interior order.
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

    Host computation (SciPy's generalised ``eigh``, float64, ``O((3 n_i)^3)``), memory
    ``4 (3 n_i)^2`` bytes for the basis (see :data:`DENSE_MAX_DOFS`).

    Parameters
    ----------
    op : ElasticOperator
    lam_ii, mu_ii : tuples of (R_k, S_k, 3, 3) arrays
        Sliced ELL blocks of ``K_ii`` for ``lam = 1, mu = 0`` and ``lam = 0, mu = 1``
        (:meth:`bayesreg.fem.stiffness.GroupBlocks.group` of a single group).

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

    check_blocks("lam_ii", lam_ii, op.cols_ii)
    check_blocks("mu_ii", mu_ii, op.cols_ii)

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

"""The matrix-free stiffness operator of the condensed FE system ``K_ii u_i = -K_ib u_b``.

:class:`ElasticOperator` stores the interior rows of ``K`` (paper Eqs. 5-7) as 3x3 blocks
in a sliced ELL layout, linear in the per-element Lamé parameters: the unit element
matrices ``klam``, ``kmu`` are kept, and the blocks at any ``lam``, ``mu`` are their
weighted sums (:meth:`ElasticOperator.blocks`).  :func:`ell_matvec` is the mat-vec of the
CG solve (:mod:`bayesreg.fem.solver`).  With few parameter groups (uniform, per tissue),
:class:`GroupBlocks` holds per-group unit blocks so that the blocks at new parameters are a
sum over groups rather than over elements.

Conventions: nodes ``(N, 3)`` world mm, tets ``(M, 4)``, DOF order ``3*i + axis``; the
reference (SciPy) assembly of the whole ``K`` is :func:`bayesreg.fem.element.stiffness_matrix`.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from bayesreg._checks import as_index_array
from bayesreg.fem.element import check_mesh, unit_element_stiffness

__all__ = ["ElasticOperator", "GroupBlocks", "ELL_SLICES", "build_operator", "ell_matvec",
           "ell_diagonal", "ell_dense", "ell_sparse", "group_blocks", "check_blocks"]


ELL_SLICES = 4
"""Row slices of the sliced ELL layout (:class:`ElasticOperator`)."""


class ElasticOperator(NamedTuple):
    """Static, parameter-independent data of the condensed FE system ``K_ii u_i = -K_ib u_b``.

    Rows are the interior nodes; ``K_ii`` and ``K_ib`` are stored as 3x3 blocks in a
    *sliced* ELL form: the rows sorted by their number of neighbours (decreasing) and cut
    into :data:`ELL_SLICES` slices of equal row count, each slice an ELL array with its own
    number of neighbour slots (its widest row's), padded with a zero block pointing at a
    dummy entry.  The mat-vec needs no scatter (:func:`ell_matvec`: one gather of the
    neighbours per slice, one gather restoring the row order).  Against one ELL array as
    wide as the widest row, it stores 40% fewer ``K_ii`` slots and 56% fewer ``K_ib`` slots
    at the paper's size (the widest rows hold 24 and 12 blocks, the mean 11.7 and 2.8; a
    third of the interior rows have no boundary neighbour).  The diagonal block of each
    ``K_ii`` row is its slot 0.  The blocks are linear in the per-element Lamé parameters:
    ``blocks(lam, mu) = segment_sum(lam_e K^lam_e + mu_e K^mu_e)``.

    A block array of this layout (``b_ii``, ``b_ib`` throughout) is a tuple of one
    ``(R_k, S_k, 3, 3)`` array per slice.

    Attributes
    ----------
    klam, kmu : (M, 4, 4, 3, 3)
        Unit element blocks (multiply ``lam_e`` resp. ``mu_e``).
    slot_ii, slot_ib : (M, 4, 4) int
        Flat destination of each element block in the concatenation of the flattened
        slices of ``K_ii`` (resp. ``K_ib``); the total number of slots is a discard bin.
    cols_ii : tuple of (R_k, S_k) int
        Interior column of each slot, per slice (padded with ``n_i``).
    cols_ib : tuple of (R_k, S_k) int
        Boundary column (padded with ``n_b``), per slice of the ``K_ib`` row order.
    row_ii, row_ib : (n_i,) int
        Position of interior row ``r`` in the concatenated slices of ``K_ii`` (resp.
        ``K_ib``, whose rows are sorted by their own number of boundary neighbours).
    boundary : (n_b,) int or None
        The boundary node indices, in the column order of ``K_ib`` (as given to
        :func:`build_operator`); its shape gives ``n_b`` statically, for the shape checks
        of the solver (``None`` on an operator built without it: no check).
    """

    klam: jax.Array
    kmu: jax.Array
    slot_ii: jax.Array
    slot_ib: jax.Array
    cols_ii: tuple
    cols_ib: tuple
    row_ii: jax.Array
    row_ib: jax.Array
    boundary: jax.Array | None = None

    @property
    def n_interior(self) -> int:
        return self.row_ii.shape[0]

    @property
    def n_boundary(self) -> int | None:
        """``n_b`` (``None`` where the operator does not hold :attr:`boundary`)."""
        return None if self.boundary is None else self.boundary.shape[0]

    @property
    def n_elements(self) -> int:
        return self.klam.shape[0]

    def blocks(self, lam_e, mu_e):
        """Sliced ELL blocks ``(b_ii, b_ib)`` of ``K_ii`` and ``K_ib`` for per-element
        ``lam_e``, ``mu_e`` (``(M,)``): tuples of ``(R_k, S_k, 3, 3)`` arrays.

        Raises
        ------
        ValueError
            ``lam_e`` or ``mu_e`` not of shape ``(M,)`` (a static check: their values are
            not checked, they may be traced).
        """
        m = self.n_elements
        for name, value in (("lam_e", lam_e), ("mu_e", mu_e)):
            if jnp.shape(value) != (m,):
                raise ValueError(f"{name} must have shape ({m},) (one value per element), "
                                 f"got {jnp.shape(value)}")
        ke = lam_e[:, None, None, None, None] * self.klam + mu_e[:, None, None, None, None] * self.kmu
        ke = ke.reshape(-1, 3, 3)
        out = []
        for slot, cols in ((self.slot_ii, self.cols_ii), (self.slot_ib, self.cols_ib)):
            total = sum(c.size for c in cols)
            flat = jax.ops.segment_sum(ke, slot.reshape(-1), num_segments=total + 1)[:-1]
            out.append(_split_slices(flat, cols))
        return tuple(out)


def _split_slices(flat, cols):
    """``(P, ...)`` -> one ``(R_k, S_k, ...)`` array per slice of ``cols``."""
    out, off = [], 0
    for c in cols:
        out.append(flat[off:off + c.size].reshape(c.shape + flat.shape[1:]))
        off += c.size
    return tuple(out)


def ell_matvec(blocks, cols, rows, x):
    """``y[r] = sum_s K[r, s] @ x[cols[r, s]]`` in the sliced ELL layout (:class:`ElasticOperator`).

    Parameters
    ----------
    blocks : tuple of (R_k, S_k, 3, 3)
    cols : tuple of (R_k, S_k) int
        Columns into ``x``; the padding column ``C`` reads a zero row.
    rows : (R,) int
        Position of each output row in the concatenated slices.
    x : (C, 3)

    Returns
    -------
    (R, 3)
    """
    xp = jnp.concatenate([x, jnp.zeros((1, 3), x.dtype)], axis=0)
    y = [jnp.sum(b * xp[c][:, :, None, :], axis=(1, 3)) for b, c in zip(blocks, cols)]
    return jnp.concatenate(y, axis=0)[rows]


def ell_diagonal(b_ii, rows):
    """Diagonal 3x3 blocks ``(R, 3, 3)`` of ``K_ii`` in the sliced ELL layout (slot 0 of each row)."""
    return jnp.concatenate([b[:, 0] for b in b_ii], axis=0)[rows]


def _slot_rows(cols):
    """The row (in the concatenated slices' order) of every ELL slot, flattened as the
    slices' ``cols`` are, and the number of concatenated rows."""
    starts = np.cumsum([0] + [x.shape[0] for x in cols])
    pos = np.concatenate([s + np.repeat(np.arange(x.shape[0]), x.shape[1]) for s, x in zip(starts, cols)])
    return pos, int(starts[-1])


def ell_dense(blocks, cols, rows, n_cols):
    """Dense ``(3R, 3 n_cols)`` matrix of sliced ELL 3x3 blocks (padding column ``n_cols`` dropped)."""
    n_rows = rows.shape[0]
    b = jnp.concatenate([x.reshape(-1, 3, 3) for x in blocks], axis=0)
    c = jnp.concatenate([x.reshape(-1) for x in cols])
    # assembled in the concatenated row order, then the row order restored (as ell_matvec)
    pos, _ = _slot_rows(cols)
    dense = jnp.zeros((n_rows, n_cols + 1, 3, 3), b.dtype).at[pos, c].add(b)[rows, :n_cols]
    return dense.transpose(0, 2, 1, 3).reshape(3 * n_rows, 3 * n_cols)


def ell_sparse(blocks, cols, rows, n_cols):
    """The matrix of :func:`ell_dense` as a SciPy CSR matrix ``(3R, 3 n_cols)`` (host code)."""
    import scipy.sparse as sp

    b = np.concatenate([np.asarray(x).reshape(-1, 3, 3) for x in blocks], axis=0)
    c = np.concatenate([np.asarray(x).reshape(-1) for x in cols])
    pos, n_concat = _slot_rows(cols)
    # the concatenated row order back to the rows' order: row r sits at position rows[r]
    row_of = np.full(n_concat, -1, dtype=np.int64)
    row_of[np.asarray(rows)] = np.arange(len(rows))
    keep = (c < n_cols) & (row_of[pos] >= 0)  # the padding column reads a zero row
    r_node, c_node, b = row_of[pos[keep]], c[keep], b[keep]
    i = (3 * r_node[:, None, None] + np.arange(3)[None, :, None]).repeat(3, axis=2)
    j = (3 * c_node[:, None, None] + np.arange(3)[None, None, :]).repeat(3, axis=1)
    return sp.csr_matrix((b.ravel(), (i.ravel(), j.ravel())), shape=(3 * len(rows), 3 * n_cols))


class GroupBlocks(NamedTuple):
    """Sliced ELL blocks of ``K_ii`` and ``K_ib`` per parameter group, for parameters that
    are constant on each of a few element groups (tissues, or one uniform material).

    ``K(lam, mu) = sum_g lam_g K^lam_g + mu_g K^mu_g`` (paper Eqs. 5-7 are linear in the
    Lamé parameters), so the blocks of one position are ``2G`` scaled sums of these shared
    arrays: no per-element ``(M, 4, 4, 3, 3)`` intermediate and no scatter per evaluation.
    Under ``vmap`` over many chains the arrays are shared, and the memory per chain is that
    of the combined blocks: the compiled log-density's scratch per chain on the
    3,395-node mesh fell from 26 to 14 MB (CPU), and 1,024 chains of the 8,938-node mesh
    on an 80 GB GPU from a failed 70.8 GiB allocation to a 55 GB peak.

    Attributes
    ----------
    lam_ii, mu_ii : tuple of (G, R_k, S_k, 3, 3)
        Blocks of ``K_ii`` for ``lam_g = 1`` (resp. ``mu_g = 1``) on group ``g``, 0 elsewhere,
        per slice of :class:`ElasticOperator`'s layout.
    lam_ib, mu_ib : tuple of (G, R_k, S_k, 3, 3)
        The same for ``K_ib``.
    """

    lam_ii: tuple
    mu_ii: tuple
    lam_ib: tuple
    mu_ib: tuple

    def group(self, g: int):
        """Unit blocks ``(lam_ii, mu_ii)`` of group ``g`` alone (tuples of ``(R_k, S_k, 3, 3)``)."""
        return tuple(a[g] for a in self.lam_ii), tuple(a[g] for a in self.mu_ii)

    def combine(self, lam_g, mu_g):
        """Blocks ``(b_ii, b_ib)`` of ``K_ii``, ``K_ib`` for per-group ``lam_g``, ``mu_g`` ``(G,)``.

        ``b_ii`` is materialised once (``optimization_barrier``): XLA:CPU otherwise fused
        the combination into the first residual ``b - K_ii x0`` as well as computing it for
        the CG loop, reading the ``2G`` unit arrays twice.  ``b_ib`` has one consumer (the
        right-hand side) and stays fused into it.
        """
        def comb(lam_u, mu_u):
            return tuple(jnp.tensordot(lam_g, a, axes=1) + jnp.tensordot(mu_g, b, axes=1)
                         for a, b in zip(lam_u, mu_u))

        return jax.lax.optimization_barrier(comb(self.lam_ii, self.mu_ii)), comb(self.lam_ib, self.mu_ib)


def group_blocks(op: ElasticOperator, group, n_groups: int) -> GroupBlocks:
    """Per-group unit blocks of ``op`` (see :class:`GroupBlocks`).

    Parameters
    ----------
    op : ElasticOperator
    group : (M,) array_like of int
        Parameter group of each element, in ``[0, n_groups)``.
    n_groups : int

    Returns
    -------
    GroupBlocks
        Memory ``144 G (P_ii + P_ib)`` bytes, ``P`` the number of slots of each layout.

    Raises
    ------
    ValueError
        ``group`` not of shape ``(M,)`` or out of range.
    """
    group = np.asarray(group)
    m = op.klam.shape[0]
    if group.shape != (m,) or (m and (group.min() < 0 or group.max() >= n_groups)):
        span = f", values {group.min()}..{group.max()}" if group.size else ""
        raise ValueError(f"group must have shape ({m},) with values in [0, {n_groups}), "
                         f"got shape {group.shape}{span}")
    zero = jnp.zeros(m, op.klam.dtype)
    blocks = jax.jit(lambda o, lam_e, mu_e: o.blocks(lam_e, mu_e))  # one program for all 2G
    lam_ii, mu_ii, lam_ib, mu_ib = [], [], [], []
    for g in range(n_groups):
        ind = jnp.asarray(group == g, op.klam.dtype)
        (a_ii, a_ib), (b_ii, b_ib) = blocks(op, ind, zero), blocks(op, zero, ind)
        lam_ii.append(a_ii), lam_ib.append(a_ib), mu_ii.append(b_ii), mu_ib.append(b_ib)

    def stack(per_group):
        return tuple(jnp.stack(s) for s in zip(*per_group))

    return GroupBlocks(stack(lam_ii), stack(mu_ii), stack(lam_ib), stack(mu_ib))


def _sliced_layout(neighbours, n_pad, n_slices):
    """Sliced ELL layout of rows with the given ordered neighbour lists.

    Returns ``(cols, rows, slot_of, n_slots)``: the per-slice ``(R_k, S_k)`` column arrays
    (padded with ``n_pad``), the concatenated position of each row ``(n,)``,
    ``{(row, col): flat slot}`` and the number of slots (the discard bin's index).
    Rows are sorted by decreasing degree (stable) and cut into ``min(n_slices, n)`` slices
    of equal count (one empty slice when ``n = 0``).
    """
    n = len(neighbours)
    degree = np.array([len(s) for s in neighbours], np.int64)
    order = np.argsort(-degree, kind="stable")
    bounds = np.linspace(0, n, max(1, min(n_slices, n)) + 1).astype(np.int64)
    cols, slot_of, off = [], {}, 0
    for a, b in zip(bounds[:-1], bounds[1:]):
        width = int(max(1, degree[order[a]])) if b > a else 1
        c = np.full((b - a, width), n_pad, np.int64)
        for j, r in enumerate(order[a:b]):
            for s, col in enumerate(neighbours[r]):
                c[j, s] = col
                slot_of[(r, col)] = off + j * width + s
        cols.append(jnp.asarray(c, dtype=jnp.int32))
        off += c.size
    rows = np.empty(n, np.int64)
    rows[order] = np.arange(n)
    return tuple(cols), jnp.asarray(rows, dtype=jnp.int32), slot_of, off


def build_operator(nodes, tets, boundary):
    """Precompute the ELL layout of the interior rows of ``K`` (see :class:`ElasticOperator`).

    Parameters
    ----------
    nodes : (N, 3) array_like
        World mm.
    tets : (M, 4) array_like of int
    boundary : (n_b,) array_like of int, or (N,) array_like of bool
        Boundary (Dirichlet, sampled) node indices, distinct, in ``[0, N)``, at least one
        (integral floats are accepted); their order is the column order of ``K_ib``.  A
        boolean mask of length ``N`` stands for the indices where it is true (in increasing
        order).  All other nodes are interior.

    Returns
    -------
    op : ElasticOperator
    interior : (n_i,) ndarray of int
        Interior node indices, in the row order of ``op``.

    Raises
    ------
    ValueError
        As :func:`bayesreg.fem.element.shape_gradients`, or ``boundary`` not 1-D, not integer (nor integral
        floats, nor a boolean mask of length ``N``), empty, with repeated indices or with
        indices outside ``[0, N)``.

    Examples
    --------
    A cube of 12 tetrahedra around one interior node (its centre):

    >>> import numpy as np
    >>> from bayesreg.mesh.tetmesh import boundary_nodes, orient_tets
    >>> from bayesreg.fem.stiffness import build_operator
    >>> corners = np.array([[x, y, z] for x in (0.0, 20.0) for y in (0.0, 20.0) for z in (0.0, 20.0)])
    >>> nodes = np.vstack([corners, [[10.0, 10.0, 10.0]]])
    >>> faces = [(0, 1, 3, 2), (4, 5, 7, 6), (0, 1, 5, 4), (2, 3, 7, 6), (0, 2, 6, 4), (1, 3, 7, 5)]
    >>> tets = orient_tets(nodes, np.array([t for a, b, c, d in faces for t in ([a, b, c, 8], [a, c, d, 8])]))
    >>> op, interior = build_operator(nodes, tets, boundary_nodes(tets))
    >>> op.n_interior, interior.tolist()
    (1, [8])
    """
    nodes, tets = check_mesh(nodes, tets)
    n = len(nodes)
    boundary = _check_boundary(boundary, n)
    is_b = np.zeros(n, bool)
    is_b[boundary] = True
    interior = np.flatnonzero(~is_b)
    pos = np.full(n, -1, np.int64)
    pos[interior] = np.arange(len(interior))
    pos[boundary] = np.arange(len(boundary))
    n_i, n_b = len(interior), len(boundary)

    klam, kmu = unit_element_stiffness(nodes, tets)
    m = len(tets)
    klam = klam.reshape(m, 4, 3, 4, 3).transpose(0, 1, 3, 2, 4)
    kmu = kmu.reshape(m, 4, 3, 4, 3).transpose(0, 1, 3, 2, 4)

    # neighbour lists per interior row, split into interior and boundary columns
    a_idx, b_idx = np.meshgrid(np.arange(4), np.arange(4), indexing="ij")
    rows = tets[:, a_idx]  # (M, 4, 4) row node
    cols = tets[:, b_idx]  # (M, 4, 4) column node
    row_int = ~is_b[rows]
    nb_ii = [set() for _ in range(n_i)]
    nb_ib = [set() for _ in range(n_i)]
    for r, c in zip(rows[row_int], cols[row_int]):
        (nb_ib if is_b[c] else nb_ii)[pos[r]].add(pos[c])
    # the diagonal block first in each K_ii row (ell_diagonal reads slot 0)
    nb_ii = [[r] + sorted(s - {r}) for r, s in enumerate(nb_ii)]
    nb_ib = [sorted(s) for s in nb_ib]
    cols_ii, row_ii, slot_of_ii, p_ii = _sliced_layout(nb_ii, n_i, ELL_SLICES)
    cols_ib, row_ib, slot_of_ib, p_ib = _sliced_layout(nb_ib, n_b, ELL_SLICES)
    slot_ii = np.full((m, 4, 4), p_ii, np.int64)
    slot_ib = np.full((m, 4, 4), p_ib, np.int64)
    for e, a, b in zip(*np.nonzero(row_int)):
        r, c = pos[rows[e, a, b]], pos[cols[e, a, b]]
        if is_b[cols[e, a, b]]:
            slot_ib[e, a, b] = slot_of_ib[(r, c)]
        else:
            slot_ii[e, a, b] = slot_of_ii[(r, c)]
    op = ElasticOperator(
        klam=jnp.asarray(klam),
        kmu=jnp.asarray(kmu),
        slot_ii=jnp.asarray(slot_ii, dtype=jnp.int32),
        slot_ib=jnp.asarray(slot_ib, dtype=jnp.int32),
        cols_ii=cols_ii,
        cols_ib=cols_ib,
        row_ii=row_ii,
        row_ib=row_ib,
        boundary=jnp.asarray(boundary, dtype=jnp.int32),
    )
    return op, interior


def _check_boundary(boundary, n):
    """Boundary node indices ``(n_b,)`` int64 from indices or a boolean mask (see
    :func:`build_operator`)."""
    boundary = np.asarray(boundary)
    if boundary.ndim != 1:
        raise ValueError(f"boundary must be a 1-D array of node indices (n_b,) or a boolean mask "
                         f"({n},), got shape {boundary.shape}")
    if boundary.dtype == np.bool_:
        if boundary.shape != (n,):
            raise ValueError(f"a boolean boundary mask must have shape ({n},) (one entry per node), "
                             f"got {boundary.shape}")
        boundary = np.flatnonzero(boundary)
    boundary = as_index_array(boundary, "boundary")
    if boundary.size == 0:
        raise ValueError("boundary must hold at least one node index (with no Dirichlet node "
                         "K_ii is singular), got none")
    if boundary.min() < 0 or boundary.max() >= n:
        raise ValueError(f"boundary node indices must lie in [0, {n}), got values "
                         f"{boundary.min()}..{boundary.max()}")
    uniq, counts = np.unique(boundary, return_counts=True)
    if np.any(counts > 1):
        raise ValueError(f"boundary node indices must be distinct, got repeated index(es) "
                         f"{uniq[counts > 1][:10].tolist()}")
    return boundary


def check_blocks(name, blocks, cols):
    """The ELL blocks ``name`` match the sliced layout of ``cols`` (``op.cols_ii`` or
    ``op.cols_ib``): one ``(R_k, S_k, 3, 3)`` array per slice."""
    expected = [tuple(c.shape) + (3, 3) for c in cols]
    got = ([jnp.shape(b) for b in blocks] if isinstance(blocks, (tuple, list))
           else type(blocks).__name__)
    if got != expected:
        raise ValueError(f"{name} must be a tuple of one array per slice of op's layout with "
                         f"shapes {expected}, got {got}")

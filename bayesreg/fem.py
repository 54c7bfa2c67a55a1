"""Linear-elastic finite elements on linear tetrahedra (paper Eqs. 2-7).

Conventions (used throughout :mod:`bayesreg`):

* ``nodes``: ``(N, 3)`` float, world coordinates in mm.
* ``tets``: ``(M, 4)`` int, positively oriented (``det[x1-x0, x2-x0, x3-x0] > 0``).
* displacements ``u``: ``(N, 3)`` mm; flattened DOF order is node-major, ``3*i + axis``.
* ``lam``, ``mu``: Lamé parameters per element, ``(M,)`` (a scalar broadcasts).  Their unit
  is arbitrary (only ratios matter for the FE solve, paper Sec. 3.3); energies are in
  ``[lam] * mm^3``.

The NumPy/SciPy functions here are the reference implementation (assembly for tests and
inspection).  :class:`ElasticOperator` is the JAX, matrix-free form used by the solver and
the log-density: a 3x3-block sliced ELL layout of the interior rows of ``K``, linear in
the per-element ``lam`` and ``mu``.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import scipy.sparse as sp

from bayesreg import _xla

_xla.configure()
import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402

__all__ = [
    "shape_gradients",
    "element_stiffness",
    "element_stiffness_voigt",
    "stiffness_matrix",
    "strain_energy",
    "strain_energy_density",
    "ElasticOperator",
    "GroupBlocks",
    "ELL_SLICES",
    "build_operator",
    "ell_matvec",
    "ell_diagonal",
    "ell_dense",
    "group_blocks",
    "element_strain_energy",
]

# d N_a / d xi for the reference tetrahedron, N = (1 - xi - eta - zeta, xi, eta, zeta).
_DN_DXI = np.array([[-1.0, -1.0, -1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])


def _check_mesh(nodes, tets):
    """``(nodes float64 (N, 3), tets int64 (M, 4))``, validated (host arrays only).

    Raises ``ValueError`` on a wrong shape, non-finite node coordinates, ``tets`` neither
    integer nor integral floats, or node indices outside ``[0, N)``."""
    try:
        nodes = np.asarray(nodes, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"nodes must be a (N, 3) array of floats, got {np.asarray(nodes).dtype}") from None
    tets = np.asarray(tets)
    if nodes.ndim != 2 or nodes.shape[1] != 3:
        raise ValueError(f"nodes must have shape (N, 3), got {nodes.shape}")
    if tets.ndim != 2 or tets.shape[1] != 4:
        raise ValueError(f"tets must have shape (M, 4), got {tets.shape}")
    if not np.all(np.isfinite(nodes)):
        bad = np.flatnonzero(~np.all(np.isfinite(nodes), axis=1))
        raise ValueError(f"nodes must be finite, got NaN or inf at node(s) {bad[:10].tolist()}")
    tets = _as_index_array(tets, "tets")
    if tets.size and (tets.min() < 0 or tets.max() >= len(nodes)):
        raise ValueError(f"tets reference node indices outside [0, {len(nodes)}), got values "
                         f"{tets.min()}..{tets.max()}")
    return nodes, tets


def _as_index_array(a, name):
    """``a`` as int64 if it is an integer array or floats that are exactly integral."""
    a = np.asarray(a)
    if np.issubdtype(a.dtype, np.integer):
        return a.astype(np.int64)
    if np.issubdtype(a.dtype, np.floating) and np.all(np.isfinite(a)) and np.all(a == np.round(a)):
        return a.astype(np.int64)
    raise ValueError(f"{name} must hold integer node indices (an integer dtype, or integral "
                     f"floats), got dtype {a.dtype}"
                     + (" with non-integral values" if np.issubdtype(a.dtype, np.floating) else ""))


def _per_element(value, m, name):
    """``value`` as ``(m,)`` float64 (a scalar broadcasts); finite and ``>= 0`` (host arrays
    only: the JAX functions used by the log-density take any values)."""
    value = np.asarray(value, dtype=np.float64)
    if value.ndim == 0:
        value = np.full(m, float(value))
    elif value.shape != (m,):
        raise ValueError(f"{name} must be a scalar or have shape ({m},), got {value.shape}")
    if not np.all(np.isfinite(value) & (value >= 0)):
        bad = value[~(np.isfinite(value) & (value >= 0))]
        raise ValueError(f"{name} must be finite and >= 0, got {bad[0]} "
                         f"({len(bad)} of {m} values bad)")
    return value


def shape_gradients(nodes, tets):
    """Gradients of the linear shape functions and element volumes.

    Parameters
    ----------
    nodes : (N, 3) array_like
        Node coordinates, world mm.
    tets : (M, 4) array_like of int
        Element connectivity.

    Returns
    -------
    grads : (M, 4, 3) ndarray
        ``grads[e, a] = grad N_a`` on element ``e`` (1/mm).
    volumes : (M,) ndarray
        Signed volumes (mm^3); positive for positively oriented elements.

    Raises
    ------
    ValueError
        On malformed shapes, non-finite node coordinates, non-integer ``tets`` or node
        indices outside ``[0, N)``, or a degenerate (zero-volume) element.
    """
    nodes, tets = _check_mesh(nodes, tets)
    x = nodes[tets]  # (M, 4, 3)
    jac = np.stack([x[:, 1] - x[:, 0], x[:, 2] - x[:, 0], x[:, 3] - x[:, 0]], axis=-1)
    det = np.linalg.det(jac)
    degenerate = np.abs(det) <= 1e-12 * np.max(np.abs(det), initial=1.0)
    if np.any(degenerate):
        raise ValueError(f"{int(np.sum(degenerate))} degenerate element(s), e.g. element "
                         f"{int(np.flatnonzero(degenerate)[0])}")
    inv = np.linalg.inv(jac)  # (M, 3, 3): rows d xi / d x
    grads = np.einsum("aj,mjk->mak", _DN_DXI, inv)
    return grads, det / 6.0


def element_stiffness(nodes, tets, lam, mu):
    """Element stiffness matrices ``K_e = V_e B_e^T C_e B_e`` (paper Eq. 6).

    Written in index form, ``K_e[3a+i, 3b+j] = V (lam g_ai g_bj + mu (g_aj g_bi +
    delta_ij g_a . g_b))`` with ``g_a = grad N_a``; identical to the Voigt form of Eqs. 4-6
    (see :func:`element_stiffness_voigt`).

    Parameters
    ----------
    nodes : (N, 3) array_like
    tets : (M, 4) array_like of int
    lam, mu : float or (M,) array_like
        Lamé parameters per element (finite, ``>= 0``).

    Returns
    -------
    (M, 12, 12) ndarray
        Local DOF order ``3*a + axis`` for local node ``a``.

    Raises
    ------
    ValueError
        As :func:`shape_gradients`, or ``lam``/``mu`` not a scalar or ``(M,)``, non-finite
        or negative.
    """
    klam, kmu = _unit_element_stiffness(nodes, tets)
    m = klam.shape[0]
    lam = _per_element(lam, m, "lam")
    mu = _per_element(mu, m, "mu")
    return lam[:, None, None] * klam + mu[:, None, None] * kmu


def _unit_element_stiffness(nodes, tets):
    """The parts of ``K_e`` multiplying ``lam`` and ``mu`` (``(M, 12, 12)`` each)."""
    g, vol = shape_gradients(nodes, tets)
    vol = np.abs(vol)
    m = g.shape[0]
    klam = np.einsum("m,mai,mbj->maibj", vol, g, g).reshape(m, 12, 12)
    gg = np.einsum("mak,mbk->mab", g, g)
    kmu = np.einsum("m,maj,mbi->maibj", vol, g, g) + np.einsum(
        "m,mab,ij->maibj", vol, gg, np.eye(3)
    )
    return klam, kmu.reshape(m, 12, 12)


def strain_displacement_matrix(grads):
    """The Voigt strain-displacement matrix ``B`` of paper Eq. 4 for linear tetrahedra.

    Parameters
    ----------
    grads : (M, 4, 3) array_like
        Shape-function gradients from :func:`shape_gradients`.

    Returns
    -------
    (M, 6, 12) ndarray
        Rows ``[e_xx, e_yy, e_zz, g_xy, g_xz, g_yz]`` (engineering shear strains).
    """
    g = np.asarray(grads)
    b = np.zeros((g.shape[0], 6, 12))
    for a in range(4):
        gx, gy, gz = g[:, a, 0], g[:, a, 1], g[:, a, 2]
        c = 3 * a
        b[:, 0, c] = gx
        b[:, 1, c + 1] = gy
        b[:, 2, c + 2] = gz
        b[:, 3, c], b[:, 3, c + 1] = gy, gx
        b[:, 4, c], b[:, 4, c + 2] = gz, gx
        b[:, 5, c + 1], b[:, 5, c + 2] = gz, gy
    return b


def material_matrix(lam, mu):
    """Isotropic material matrix ``C`` of paper Eq. 5, shape ``(6, 6)``."""
    c = np.zeros((6, 6))
    c[:3, :3] = lam
    c[[0, 1, 2], [0, 1, 2]] = lam + 2 * mu
    c[[3, 4, 5], [3, 4, 5]] = mu
    return c


def element_stiffness_voigt(nodes, tets, lam, mu):
    """``V_e B^T C B`` assembled literally from paper Eqs. 4-6 (a slow reference).

    Same signature, result and errors as :func:`element_stiffness`.
    """
    g, vol = shape_gradients(nodes, tets)
    b = strain_displacement_matrix(g)
    m = len(vol)
    lam = _per_element(lam, m, "lam")
    mu = _per_element(mu, m, "mu")
    c = np.stack([material_matrix(l_, m_) for l_, m_ in zip(lam, mu)])
    return np.abs(vol)[:, None, None] * np.einsum("mki,mkl,mlj->mij", b, c, b)


def _dof_index(tets):
    return (3 * np.asarray(tets)[:, :, None] + np.arange(3)).reshape(len(tets), 12)


def stiffness_matrix(nodes, tets, lam, mu):
    """Global stiffness matrix ``K`` (paper Eq. 7) as SciPy sparse CSR.

    Parameters
    ----------
    nodes : (N, 3) array_like
        World mm.
    tets : (M, 4) array_like of int
    lam, mu : float or (M,) array_like
        Lamé parameters, per element or uniform (finite, ``>= 0``).

    Returns
    -------
    scipy.sparse.csr_array, shape (3N, 3N)
        Symmetric positive semi-definite; its null space holds the six rigid-body modes.

    Raises
    ------
    ValueError
        As :func:`element_stiffness`.
    """
    nodes, tets = _check_mesh(nodes, tets)
    ke = element_stiffness(nodes, tets, lam, mu)
    dof = _dof_index(tets)
    rows = np.repeat(dof, 12, axis=1).ravel()
    cols = np.tile(dof, (1, 12)).ravel()
    n = 3 * len(nodes)
    return sp.csr_array(sp.coo_array((ke.ravel(), (rows, cols)), shape=(n, n)))


def strain_energy(nodes, tets, u, lam, mu):
    """Linear-elastic strain energy ``E_r`` (paper Eqs. 2-3).

    Parameters
    ----------
    nodes : (N, 3) array_like
        World mm.
    tets : (M, 4) array_like of int
    u : (N, 3) array_like
        Nodal displacements, mm.
    lam, mu : float or (M,) array_like
        Finite, ``>= 0``.

    Returns
    -------
    float
        ``sum_e V_e (mu eps:eps + lam/2 tr(eps)^2)`` = ``u^T K u / 2``, in ``[lam] mm^3``.

    Raises
    ------
    ValueError
        As :func:`element_stiffness`, or ``u`` not of shape ``(N, 3)``.
    """
    nodes, tets = _check_mesh(nodes, tets)
    u = np.asarray(u, dtype=np.float64)
    if u.shape != nodes.shape:
        raise ValueError(f"u must have shape {nodes.shape}, got {u.shape}")
    g, vol = shape_gradients(nodes, tets)
    m = len(vol)
    dens = strain_energy_density(
        jnp.asarray(g), jnp.asarray(u[tets]), _per_element(lam, m, "lam"), _per_element(mu, m, "mu")
    )
    return float(np.sum(np.abs(vol) * np.asarray(dens)))


def strain_energy_density(grads, u_e, lam, mu):
    """Energy density per element ``mu eps:eps + lam/2 (div u)^2`` (paper Eq. 2 integrand).

    Parameters
    ----------
    grads : (M, 4, 3) array
        Shape-function gradients.
    u_e : (M, 4, 3) array
        Displacements of each element's nodes, mm.
    lam, mu : (M,) array

    Returns
    -------
    (M,) jax array
        Constant within each linear element.
    """
    du = jnp.sum(u_e[:, :, :, None] * grads[:, :, None, :], axis=1)  # du[i, j] = d u_i / d x_j
    eps = 0.5 * (du + jnp.swapaxes(du, 1, 2))
    tr = eps[:, 0, 0] + eps[:, 1, 1] + eps[:, 2, 2]
    return mu * jnp.sum(eps * eps, axis=(1, 2)) + 0.5 * lam * tr * tr


def element_strain_energy(grads, volumes, u_e, lam, mu):
    """JAX strain energy ``E_r`` summed over elements (see :func:`strain_energy`)."""
    return jnp.sum(volumes * strain_energy_density(grads, u_e, lam, mu))


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


def ell_dense(blocks, cols, rows, n_cols):
    """Dense ``(3R, 3 n_cols)`` matrix of sliced ELL 3x3 blocks (padding column ``n_cols`` dropped)."""
    n_rows = rows.shape[0]
    b = jnp.concatenate([x.reshape(-1, 3, 3) for x in blocks], axis=0)
    c = jnp.concatenate([x.reshape(-1) for x in cols])
    # assembled in the concatenated row order, then the row order restored (as ell_matvec)
    starts = np.cumsum([0] + [x.shape[0] for x in cols])
    pos = np.concatenate([s + np.repeat(np.arange(x.shape[0]), x.shape[1]) for s, x in zip(starts, cols)])
    dense = jnp.zeros((n_rows, n_cols + 1, 3, 3), b.dtype).at[pos, c].add(b)[rows, :n_cols]
    return dense.transpose(0, 2, 1, 3).reshape(3 * n_rows, 3 * n_cols)


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
        As :func:`shape_gradients`, or ``boundary`` not 1-D, not integer (nor integral
        floats, nor a boolean mask of length ``N``), empty, with repeated indices or with
        indices outside ``[0, N)``.
    """
    nodes, tets = _check_mesh(nodes, tets)
    n = len(nodes)
    boundary = _check_boundary(boundary, n)
    is_b = np.zeros(n, bool)
    is_b[boundary] = True
    interior = np.flatnonzero(~is_b)
    pos = np.full(n, -1, np.int64)
    pos[interior] = np.arange(len(interior))
    pos[boundary] = np.arange(len(boundary))
    n_i, n_b = len(interior), len(boundary)

    klam, kmu = _unit_element_stiffness(nodes, tets)
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
    boundary = _as_index_array(boundary, "boundary")
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

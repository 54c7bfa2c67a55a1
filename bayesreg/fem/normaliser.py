"""The exact normaliser of the elastic prior, ``(1/2) log pdet S(lam, mu)``, and its surrogate.

With the interior nodes at the FE solution, ``E_r = u_b^T S u_b / 2`` with
``S = K_bb - K_bi K_ii^-1 K_ib`` the Schur complement of ``K`` on the boundary DOFs, so the
prior ``exp(-E_r / T_r)`` of paper Eq. 12 is a Gaussian on ``u_b`` (on the complement of
the six rigid-body modes, the null space of ``S``) whose log-normaliser is
``(1/2) log pdet S - ((3 n_b - 6) / 2) log (2 pi T_r)``; the second term is constant.  The
paper drops the first (its Sec. 3.3), which biases the elastic parameters toward zero;
``model.prior_normaliser: exact`` adds it.

**Exact, sparse** (:func:`log_pdet_sparse`).  Ground six boundary DOFs ``J`` on which the
rigid modes ``N`` (orthonormal, ``(3 n_b, 6)``) are independent (pivoted QR of ``N^T``).
For a symmetric positive semi-definite ``S`` whose null space is spanned by ``N``,
``det S_JJ' = pdet S det(N_J)^2 / det(N^T N)`` (``J'`` the other DOFs), and ``S_J'J'`` is
the Schur complement of ``K`` without the DOFs ``J`` on its boundary DOFs, so

    (1/2) log pdet S = (1/2) [log det K_J'J' - log det K_ii] - log |det N_J|.

Both matrices are sparse and positive definite for positive Lamé parameters; their
log-determinants come from CHOLMOD's supernodal Cholesky factorisation with a
fill-reducing ordering analysed once per pattern (``sparsax.logdet``), differentiable by
the selected inverse (Takahashi's recurrence: ``d log det A = tr(A^-1 dA)`` needs ``A^-1``
on ``A``'s pattern only).  The values of both matrices are linear in the Lamé parameters:
a product with per-group unit matrices (``(nnz, 2 G)``, uniform and tissue models) or a
segment sum over the element matrices (per-element model).  Parameters for which CHOLMOD
could fail (non-finite, non-positive, or below ``1e-15`` times the largest: a stiffness
singular to round-off) are not factorised: the result is NaN, and the sampler rejects the
position as it does any hard-constraint violation.

**Surrogate** (:func:`build_surrogate`, :func:`surrogate_log_pdet`): a smooth function of
the parameters whose value and gradient cost microseconds, for the trajectories of the
gradient kernels, which a per-transition Metropolis correction with the exact value keeps
exact (:mod:`bayesreg.sampling.kernels.gibbs`; Liu 2001, *Monte Carlo Strategies in Scientific
Computing*, Sec. 9.4, "surrogate transition"; Christen and Fox 2005, *Markov chain Monte
Carlo using an approximation*).  With ``A(theta) = sum_t theta_t A_t`` (``theta`` the
``2 G`` Lamé parameters, ``A_t`` positive semi-definite) and ``v_i`` the eigenvectors of
``A(theta_0)``, ``log det A(theta) ~ sum_i log(c_i . theta)``, ``c_it = v_i^T A_t v_i``:
exact at ``theta_0`` in value and gradient, exact whenever the ``A_t`` commute, of the
right homogeneity and singular where a tissue softens to nothing.  A quadratic in
``log theta`` fitted to the remaining difference at ``theta_0`` (central differences of the
exact value) makes it second-order exact there.

The dense reference (:func:`dense_stiffness`, :func:`log_pdet_schur`: one dense float64
Cholesky factorisation of ``K`` with the rigid modes lifted, ``(3N)^3 / 3`` flops) stays
for the tests and for :func:`bayesreg.model.posterior.prior_precision`.
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import scipy.linalg as sla
import scipy.sparse as sps

__all__ = ["NormaliserData", "SparsePattern", "Surrogate", "normaliser_data", "dense_stiffness",
           "log_pdet_schur", "log_pdet_sparse", "build_surrogate", "surrogate_log_pdet",
           "add_normaliser", "trace_inverse_interior", "sparse_logdet", "SAFE_RATIO"]

#: Parameters below this fraction of the largest are not factorised (NaN; module docstring):
#: such a stiffness is singular to round-off, and CHOLMOD would stop the program.
SAFE_RATIO = 1e-15


class SparsePattern(NamedTuple):
    """One sparse symmetric matrix ``A = sum`` of element contributions, upper triangle, COO.

    Attributes
    ----------
    rows, cols : (nnz,) int32
        Row and column of each stored entry (``rows <= cols``), in the matrix's own DOFs.
    unit : (nnz, 2 G) array or None
        Values of ``A`` per unit Lamé parameter of each group, ``[lam_0.. lam_G-1,
        mu_0.. mu_G-1]`` (``None`` for the per-element model: ``src``/``dest`` instead).
    src : (E,) int32 or (0,)
        Entry of the flattened element matrices ``(M * 144,)`` (element-major, then row
        ``3a + i``, column ``3b + j``) of each element contribution that lands in ``A``.
    dest : (E,) int32 or (0,)
        Its stored entry (``[0, nnz)``).
    diag : (n,) int32
        Stored entry of each diagonal element; its length is the matrix's order ``n``.
    """

    rows: jax.Array
    cols: jax.Array
    unit: jax.Array | None
    src: jax.Array
    dest: jax.Array
    diag: jax.Array

    @property
    def n(self) -> int:
        """The matrix's order (static: a shape)."""
        return self.diag.shape[0]


class NormaliserData(NamedTuple):
    """Static data of the normaliser of one mesh (:func:`normaliser_data`).

    Attributes
    ----------
    dense_index : (M * 144,) int
        Flat position in the dense ``(3N, 3N)`` stiffness, DOFs ordered interior nodes
        first (in the operator's row order) then boundary nodes, of each entry of the
        element matrices (``klam`` / ``kmu`` of :class:`bayesreg.fem.stiffness.ElasticOperator`):
        the dense reference's.
    rigid_b : (3 n_b, 6)
        Orthonormal basis of the rigid-body modes restricted to the boundary DOFs (the
        null space of the Schur complement ``S``).
    grounded : SparsePattern
        ``K`` without the six grounded boundary DOFs ``J``: ``(3N - 6)`` square.
    interior : SparsePattern
        ``K_ii``: ``(3 n_i)`` square (empty without interior nodes).
    log_det_nj : ()
        ``log |det N_J|`` of the grounded DOFs (module docstring).
    """

    dense_index: jax.Array
    rigid_b: jax.Array
    grounded: SparsePattern
    interior: SparsePattern
    log_det_nj: jax.Array


def _rigid_modes(nodes, boundary) -> np.ndarray:
    xb = np.asarray(nodes, np.float64)[np.asarray(boundary)]
    xb = xb - xb.mean(axis=0)
    rigid = np.zeros((len(xb), 3, 6))
    for k in range(3):
        rigid[:, k, k] = 1.0
        rigid[:, :, 3 + k] = np.cross(np.eye(3)[k], xb)
    return np.linalg.qr(rigid.reshape(-1, 6))[0]


def _pattern(dof_e, new, size, klam, kmu, group, n_groups, grouped) -> SparsePattern:
    """The upper triangle of the matrix on the DOFs ``new >= 0`` (``new[d]``: its index)."""
    r = np.repeat(dof_e, 12, axis=1).reshape(-1)  # entry (e, 12 p + q): row dof_e[e, p]
    c = np.tile(dof_e, (1, 12)).reshape(-1)  # column dof_e[e, q]
    rr, cc = new[r], new[c]
    keep = (rr >= 0) & (cc >= 0) & (rr <= cc)
    src = np.flatnonzero(keep)
    key = rr[keep].astype(np.int64) * size + cc[keep]
    uniq, dest = np.unique(key, return_inverse=True)
    rows, cols = (uniq // max(size, 1)).astype(np.int32), (uniq % max(size, 1)).astype(np.int32)
    diag = np.flatnonzero(rows == cols).astype(np.int32)
    if len(diag) != size:
        raise ValueError(f"a stiffness pattern of order {size} stores {len(diag)} diagonal entries: "
                         "a DOF that no element touches")
    unit = None
    if grouped:
        unit = np.zeros((len(uniq), 2 * n_groups))
        g = np.asarray(group)[src // 144]
        np.add.at(unit, (dest, g), klam[src])
        np.add.at(unit, (dest, n_groups + g), kmu[src])
        src, dest = np.zeros(0, np.int32), np.zeros(0, np.int32)
    return SparsePattern(jnp.asarray(rows), jnp.asarray(cols),
                         None if unit is None else jnp.asarray(unit),
                         jnp.asarray(src, jnp.int32), jnp.asarray(dest, jnp.int32), jnp.asarray(diag))


def normaliser_data(nodes, tets, boundary, perm, klam, kmu, group, n_groups: int,
                    *, grouped: bool = True) -> NormaliserData:
    """:class:`NormaliserData` of a mesh.

    Parameters
    ----------
    nodes : (N, 3) array
        World mm.
    tets : (M, 4) int array
    boundary : (n_b,) int array
        Boundary node indices (at least three nodes not on one line).
    perm : (N,) int array
        Position of each node in ``concat(boundary, interior)`` (boundary first).
    klam, kmu : (M, 4, 4, 3, 3) arrays
        Unit element stiffness blocks (:class:`bayesreg.fem.stiffness.ElasticOperator`).
    group : (M,) int array
        Parameter group of each element.
    n_groups : int
        ``G``.
    grouped : bool
        Store per-group unit matrices (``G`` small); else the element map (per-element
        model).
    """
    nodes, tets = np.asarray(nodes, np.float64), np.asarray(tets)
    boundary, perm = np.asarray(boundary), np.asarray(perm)
    n, n_b = len(nodes), len(boundary)
    n_i = n - n_b
    # the dense reference's index (interior DOFs first)
    dense_pos = np.where(perm >= n_b, perm - n_b, perm + n_i)
    dof = (3 * dense_pos[tets][:, :, None] + np.arange(3)).reshape(-1, 12)
    n_dof = 3 * n
    dense_index = (dof[:, :, None] * n_dof + dof[:, None, :]).reshape(-1)
    rigid_b = _rigid_modes(nodes, boundary)
    # six grounded boundary DOFs on which the rigid modes are independent
    _, _, piv = sla.qr(rigid_b.T, pivoting=True)
    j = np.sort(piv[:6])
    log_det_nj = float(np.linalg.slogdet(rigid_b[j])[1])
    klam_f = np.asarray(klam).transpose(0, 1, 3, 2, 4).reshape(-1)  # (a, i, b, j) -> 3a+i, 3b+j
    kmu_f = np.asarray(kmu).transpose(0, 1, 3, 2, 4).reshape(-1)
    dof_e = (3 * tets[:, :, None] + np.arange(3)).reshape(-1, 12)  # node-order DOFs
    removed = np.zeros(n_dof, bool)
    removed[(3 * boundary[:, None] + np.arange(3)).reshape(-1)[j]] = True
    new_k = np.cumsum(~removed) - 1
    new_k[removed] = -1
    interior = np.setdiff1d(np.arange(n), boundary)
    new_i = np.full(n_dof, -1)
    new_i[(3 * interior[:, None] + np.arange(3)).reshape(-1)] = np.arange(3 * len(interior))
    args = (klam_f, kmu_f, group, n_groups, grouped)
    return NormaliserData(
        dense_index=jnp.asarray(dense_index, dtype=jnp.int32 if n_dof**2 < 2**31 else jnp.int64),
        rigid_b=jnp.asarray(rigid_b),
        grounded=_pattern(dof_e, new_k, n_dof - 6, *args),
        interior=_pattern(dof_e, new_i, 3 * len(interior), *args),
        log_det_nj=jnp.asarray(log_det_nj))


def _values(p: SparsePattern, klam, kmu, lam_g, mu_g, group):
    """Stored values of the matrix of pattern ``p`` at the group parameters."""
    if p.unit is not None:
        return p.unit @ jnp.concatenate([lam_g, mu_g])
    lam_e, mu_e = lam_g[group], mu_g[group]
    e = p.src // 144
    v = lam_e[e] * klam.reshape(-1)[p.src] + mu_e[e] * kmu.reshape(-1)[p.src]
    return jax.ops.segment_sum(v, p.dest, num_segments=p.rows.shape[0])


def sparse_logdet(p: SparsePattern, values, *, host: bool | None = None):
    """``log det A`` of the positive definite matrix of pattern ``p`` with stored values
    ``values`` ``(nnz,)``, by CHOLMOD (``sparsax.logdet``); differentiable in ``values``
    (reverse mode, by selected inversion).

    sparsax's XLA handlers exist for the CPU alone.  With ``host`` (default: JAX's default
    backend is not the CPU, e.g. a GPU) the factorisation runs on the host CPU through
    :func:`jax.pure_callback` (chains mapped by ``vmap`` call it once per chain), its
    gradient through a ``custom_vjp`` from the same selected inversion; the values travel
    to the host and the result back.  The same numbers either way.

    Parameters
    ----------
    p : SparsePattern
        The matrix's upper triangle (``rows``, ``cols``: ``(nnz,)``; order ``p.n``).
    values : (nnz,) float64 array
        Its stored values ([lam] mm: stiffness entries).
    host : bool, optional
        Force (``True``) or forbid (``False``) the host route; default by the backend.

    Returns
    -------
    () float64 array

    Raises
    ------
    jax.errors.JaxRuntimeError
        CHOLMOD's factorisation failed (``A`` not positive definite), when the program runs.
    """
    import sparsax

    if host is None:
        host = jax.default_backend() != "cpu"
    if not host:
        return sparsax.logdet(p.rows, p.cols, values, n=p.n)
    return _host_logdet(p.rows, p.cols, values, p.n)


@functools.partial(jax.jit, static_argnames=("n", "grad"))
def _on_cpu(r, c, v, *, n: int, grad: bool):
    """``(log det,)`` or ``(log det, d log det / d values)``: the CPU program of the host
    route, compiled once per matrix order (not once per program that calls it)."""
    import sparsax

    if grad:
        return jax.value_and_grad(lambda x: sparsax.logdet(r, c, x, n=n))(v)
    return (sparsax.logdet(r, c, v, n=n),)


def _host_call(rows, cols, values, n: int, grad: bool):
    """``(log det,)`` or ``(log det, d log det / d values)`` computed on the host CPU."""

    def on_host(r, c, v):
        cpu = jax.devices("cpu")[0]
        out = _on_cpu(*(jax.device_put(np.asarray(a), cpu) for a in (r, c, v)), n=n, grad=grad)
        return tuple(np.asarray(o, np.float64) for o in out)

    shapes = (jax.ShapeDtypeStruct((), jnp.float64),)
    if grad:
        shapes = shapes + (jax.ShapeDtypeStruct(values.shape, jnp.float64),)
    return jax.pure_callback(on_host, shapes, rows, cols, values, vmap_method="sequential")


@functools.partial(jax.custom_vjp, nondiff_argnums=(3,))
def _host_logdet(rows, cols, values, n):
    return _host_call(rows, cols, values, n, grad=False)[0]


def _host_logdet_fwd(rows, cols, values, n):
    value, grad = _host_call(rows, cols, values, n, grad=True)
    return value, (rows, cols, grad)


def _host_logdet_bwd(n, res, ct):
    rows, cols, grad = res
    return (np.zeros(rows.shape, jax.dtypes.float0), np.zeros(cols.shape, jax.dtypes.float0),
            ct * grad)


_host_logdet.defvjp(_host_logdet_fwd, _host_logdet_bwd)


def _flat(k):
    """Element blocks ``(M, 4, 4, 3, 3)`` flattened as the patterns index them."""
    return k.transpose(0, 1, 3, 2, 4).reshape(-1)


def log_pdet_sparse(data: NormaliserData, klam, kmu, lam_g, mu_g, group):
    """``(1/2) log pdet S(lam, mu)`` by two sparse Cholesky factorisations (module docstring).

    Parameters
    ----------
    data : NormaliserData
    klam, kmu : (M, 4, 4, 3, 3) arrays
        Unit element blocks.
    lam_g, mu_g : (G,) arrays
        Lamé parameters per group (every element's with the per-element model).
    group : (M,) int array

    Returns
    -------
    () array
        Differentiable in ``lam_g``, ``mu_g`` (reverse mode, by selected inversion); NaN
        where a parameter is not finite, not positive, or below :data:`SAFE_RATIO` times the
        largest (the matrices are then not factorised).
    """
    theta = jnp.concatenate([lam_g, mu_g])
    safe = jnp.all(jnp.isfinite(theta)) & jnp.all(theta > SAFE_RATIO * jnp.max(theta))
    lam_s = jnp.where(safe, lam_g, jnp.ones_like(lam_g))
    mu_s = jnp.where(safe, mu_g, jnp.ones_like(mu_g))
    kl, km = _flat(klam), _flat(kmu)

    def logdet(p: SparsePattern):
        return sparse_logdet(p, _values(p, kl, km, lam_s, mu_s, group))

    value = 0.5 * logdet(data.grounded) - data.log_det_nj
    if data.interior.n:
        value = value - 0.5 * logdet(data.interior)
    return jnp.where(safe, value, jnp.nan)


def trace_inverse_interior(data: NormaliserData, klam, kmu, lam_g, mu_g, group) -> float:
    """``tr(K_ii^-1)`` (mm / [lam]): the sum of the interior DOFs' variances under
    ``N(0, T K_ii^-1)`` per unit temperature ``T``, at the group parameters ``lam_g``,
    ``mu_g`` ``(G,)``.

    Exact: the diagonal of ``K_ii^-1`` is the gradient of ``log det K_ii`` with respect to
    its diagonal entries, which CHOLMOD's selected inversion gives (``sparsax.logdet``'s
    reverse mode) from one sparse factorisation; no dense inverse.  Host code.

    Raises
    ------
    ValueError
        No interior nodes, or the factorisation fails (non-finite result).
    """
    p = data.interior
    if p.n == 0:
        raise ValueError("tr(K_ii^-1) needs interior nodes")
    kl, km = _flat(klam), _flat(kmu)
    lam_g, mu_g = jnp.asarray(lam_g, jnp.float64), jnp.asarray(mu_g, jnp.float64)

    def logdet(values):
        return sparse_logdet(p, values)

    grad = jax.grad(logdet)(_values(p, kl, km, lam_g, mu_g, group))
    trace = float(jnp.sum(grad[p.diag]))
    if not np.isfinite(trace) or trace <= 0:
        raise ValueError(f"tr(K_ii^-1) failed (got {trace}): K_ii not positive definite at "
                         "these parameters")
    return trace


class Surrogate(NamedTuple):
    """The smooth surrogate of ``(1/2) log pdet S`` built at ``theta_0`` (:func:`build_surrogate`).

    ``g~(theta) = (1/2) [sum_i log(c_i . theta)]_grounded - (1/2) [...]_interior + offset
    + sum_t f_t(u_t) + (1/2) sum_{s != t} H_st du_s du_t``, ``u = log theta``,
    ``du = u - log theta_0``: the eigenvector part, then a correction fitted to the exact
    value: along each parameter's axis a Chebyshev interpolant ``f_t`` (``f_t(u_0t) = 0``)
    over ``[lo_t, hi_t]``, continued linearly beyond, and the mixed second derivatives at
    ``theta_0``.

    Attributes
    ----------
    c_grounded : (3N - 6, 2 G)
        ``c_it = v_i^T A_t v_i`` of the grounded stiffness (module docstring).
    c_interior : (3 n_i, 2 G)
        The same of ``K_ii``.
    offset : ()
        Constant making the surrogate's value at ``theta_0`` the exact one.
    log_theta0 : (2 G,)
        ``log theta_0``.
    lo, hi : (2 G,)
        Range of each ``f_t`` in ``u_t``.
    coef : (2 G, K)
        Chebyshev coefficients of each ``f_t`` on ``[lo_t, hi_t]`` (zero for the
        parameters that do not vary).
    slope_lo, slope_hi : (2 G,)
        ``f_t'`` at the ends (the linear continuation).
    hess : (2 G, 2 G)
        Mixed second derivatives in ``u`` at ``theta_0`` (zero diagonal).
    """

    c_grounded: jax.Array
    c_interior: jax.Array
    offset: jax.Array
    log_theta0: jax.Array
    lo: jax.Array
    hi: jax.Array
    coef: jax.Array
    slope_lo: jax.Array
    slope_hi: jax.Array
    hess: jax.Array


def _clenshaw(coef, x):
    """``sum_k coef[..., k] T_k(x)`` (Chebyshev series, Clenshaw's recurrence; ``x`` in [-1, 1])."""
    b1, b2 = jnp.zeros_like(x), jnp.zeros_like(x)
    for k in range(coef.shape[-1] - 1, 0, -1):
        b1, b2 = coef[..., k] + 2.0 * x * b1 - b2, b1
    return coef[..., 0] + x * b1 - b2


def _axis_terms(s: Surrogate, u):
    """``sum_t f_t(u_t)`` (the axis interpolants, continued linearly beyond their range)."""
    half = 0.5 * (s.hi - s.lo)
    x = (u - 0.5 * (s.hi + s.lo)) / half
    xc = jnp.clip(x, -1.0, 1.0)
    inside = _clenshaw(s.coef, xc)
    beyond = jnp.where(x > 1.0, s.slope_hi * (u - s.hi), jnp.where(x < -1.0, s.slope_lo * (u - s.lo), 0.0))
    return jnp.sum(inside + beyond)


def surrogate_log_pdet(s: Surrogate, lam_g, mu_g):
    """The surrogate's ``(1/2) log pdet S`` at the group parameters ``lam_g, mu_g`` ``(G,)``
    (positive); smooth (continuously differentiable), ``O(N G)`` flops."""
    theta = jnp.concatenate([lam_g, mu_g])
    value = 0.5 * jnp.sum(jnp.log(s.c_grounded @ theta))
    if s.c_interior.shape[0]:
        value = value - 0.5 * jnp.sum(jnp.log(s.c_interior @ theta))
    u = jnp.log(theta)
    du = u - s.log_theta0
    return value + s.offset + _axis_terms(s, u) + 0.5 * du @ s.hess @ du


_log_pdet_jit = jax.jit(log_pdet_sparse)


def _unit_matrices(p: SparsePattern) -> list:
    """The full symmetric sparse ``A_t`` (SciPy CSR) of each unit parameter of ``p``."""
    rows, cols, unit = np.asarray(p.rows), np.asarray(p.cols), np.asarray(p.unit)
    out = []
    for t in range(unit.shape[1]):
        a = sps.coo_matrix((unit[:, t], (rows, cols)), shape=(p.n, p.n)).tocsr()
        out.append((a + sps.triu(a, 1).T).tocsr())
    return out


def _eigen_part(p: SparsePattern, theta0: np.ndarray) -> np.ndarray:
    """``c_it = v_i^T A_t v_i`` for the eigenvectors ``v_i`` of ``A(theta_0)``."""
    if not p.n:
        return np.zeros((0, theta0.shape[0]))
    mats = _unit_matrices(p)
    a0 = sum(t * m for t, m in zip(theta0, mats)).toarray()
    _, v = np.linalg.eigh(a0)
    return np.stack([np.einsum("ij,ij->j", v, m @ v) for m in mats], axis=1)


def build_surrogate(data: NormaliserData, klam, kmu, group, lam_g0, mu_g0, *, free=None,
                    bounds=None, span: float = 4.0, nodes: int = 9,
                    step: float = 5e-3) -> Surrogate:
    """:class:`Surrogate` of ``(1/2) log pdet S`` at the group parameters ``lam_g0, mu_g0``.

    Two dense symmetric eigendecompositions (orders ``3N - 6`` and ``3 n_i``: about a
    second at the paper's 800 nodes) and ``1 + f nodes + 2 f (f - 1)`` exact sparse values
    (``f`` the parameters that vary) for the correction.

    Parameters
    ----------
    data : NormaliserData
        With per-group unit matrices (not the per-element model).
    klam, kmu : (M, 4, 4, 3, 3) arrays
    group : (M,) int array
    lam_g0, mu_g0 : (G,) arrays
        ``theta_0``, positive.
    free : sequence of int, optional
        Indices into ``[lam_g, mu_g]`` of the parameters that vary (default all); the
        correction is fitted along these only.
    bounds : (2 G, 2) array, optional
        Support ``(r1, r2)`` of each parameter: the axis ranges stay inside it.
    span : float
        Half-width of each axis range in ``log theta`` (4: a factor of 55 either way), where
        the poorly identified parameters (CSF's) roam.
    nodes : int
        Chebyshev nodes per axis.
    step : float
        Central-difference step in ``log theta`` of the mixed derivatives.

    Returns
    -------
    Surrogate

    Raises
    ------
    ValueError
        Per-element data (no unit matrices), or ``theta_0`` not finite and positive or one
        the exact normaliser cannot factorise.
    """
    if data.grounded.unit is None:
        raise ValueError("the normaliser's surrogate needs per-group unit matrices (uniform or "
                         "tissue model), not the per-element model")
    theta0 = np.concatenate([np.asarray(lam_g0, np.float64), np.asarray(mu_g0, np.float64)])
    if not np.all(np.isfinite(theta0) & (theta0 > 0)):
        raise ValueError(f"the surrogate's parameters must be finite and > 0, got {theta0}")
    n_p = theta0.shape[0]
    n_g = n_p // 2
    c_k, c_i = _eigen_part(data.grounded, theta0), _eigen_part(data.interior, theta0)

    def exact(th):  # one compiled program for every surrogate of a mesh's shapes
        return _log_pdet_jit(data, klam, kmu, th[:n_g], th[n_g:], group)

    def eig_part(th):
        v = 0.5 * np.sum(np.log(c_k @ th)) - (0.5 * np.sum(np.log(c_i @ th)) if len(c_i) else 0.0)
        return v - float(data.log_det_nj)

    def residual(u):
        th = np.exp(u)
        try:
            value = float(exact(jnp.asarray(th)))
        except jax.errors.JaxRuntimeError as exc:  # sparsax's Cholesky: NaN, as the dense one
            if "not positive definite" not in str(exc):
                raise
            value = np.nan
        return value - eig_part(th)

    u0 = np.log(theta0)
    r0 = residual(u0)
    if not np.isfinite(r0):
        raise ValueError(f"the exact normaliser cannot be factorised at the surrogate's "
                         f"parameters {theta0}: K is not positive definite beyond its six "
                         "rigid modes (a mesh of loose pieces, bayesreg.mesh.tetmesh.mesh_pieces, or a "
                         "parameter at 0)")
    idx = list(range(n_p) if free is None else free)
    lo, hi = u0 - span, u0 + span
    if bounds is not None:  # inside each support by a millionth of its width
        b = np.asarray(bounds, np.float64)
        finite = np.isfinite(b).all(axis=1)
        width = np.where(finite, b[:, 1] - b[:, 0], 0.0)
        lo = np.where(finite & (b[:, 0] > 0), np.maximum(lo, np.log(np.where(
            b[:, 0] > 0, b[:, 0], 1.0) + 1e-6 * width)), lo)
        hi = np.where(finite, np.minimum(hi, np.log(np.where(finite, b[:, 1], 1.0) - 1e-6 * width)), hi)
    lo, hi = np.minimum(lo, u0 - step), np.maximum(hi, u0 + step)
    # the axis interpolants: Chebyshev points of the first kind on [lo, hi]
    coef = np.zeros((n_p, nodes))
    slope_lo, slope_hi = np.zeros(n_p), np.zeros(n_p)
    x = np.cos(np.pi * (np.arange(nodes) + 0.5) / nodes)
    cheb = np.polynomial.chebyshev
    for i in idx:
        half, mid = 0.5 * (hi[i] - lo[i]), 0.5 * (hi[i] + lo[i])
        vals = []
        for xk in x:
            u = u0.copy()
            u[i] = mid + half * xk
            v = residual(u)
            if not np.isfinite(v):
                raise ValueError(f"the exact normaliser fails at {np.exp(u)} (the surrogate's "
                                 f"range of parameter {i}): narrow the prior's support")
            vals.append(v - r0)
        c = cheb.chebfit(x, np.asarray(vals), nodes - 1)
        c[0] -= cheb.chebval((u0[i] - mid) / half, c)  # f_t(u0_t) = 0
        coef[i] = c
        d = cheb.chebder(c)
        slope_lo[i], slope_hi[i] = cheb.chebval(-1.0, d) / half, cheb.chebval(1.0, d) / half
    hess = np.zeros((n_p, n_p))
    e = np.eye(n_p) * step
    for a, i in enumerate(idx):
        for j in idx[a + 1:]:
            hess[i, j] = hess[j, i] = (residual(u0 + e[i] + e[j]) - residual(u0 + e[i] - e[j])
                                       - residual(u0 - e[i] + e[j]) + residual(u0 - e[i] - e[j])
                                       ) / (4 * step**2)
    return Surrogate(jnp.asarray(c_k), jnp.asarray(c_i), jnp.asarray(r0 - float(data.log_det_nj)),
                     jnp.asarray(u0), jnp.asarray(lo), jnp.asarray(hi), jnp.asarray(coef),
                     jnp.asarray(slope_lo), jnp.asarray(slope_hi), jnp.asarray(hess))


def dense_stiffness(klam, kmu, lam_e, mu_e, data: NormaliserData, n_dof: int):
    """Dense stiffness ``K`` ``(3N, 3N)``, interior DOFs first (see
    :attr:`NormaliserData.dense_index`), from the unit element matrices ``klam``, ``kmu``
    and per-element Lamé parameters ``lam_e``, ``mu_e`` ``(M,)``.

    Memory ``72 N^2`` bytes: meant for meshes up to a few thousand nodes.
    """
    m = lam_e.shape[0]
    ke = (lam_e[:, None, None, None, None] * klam + mu_e[:, None, None, None, None] * kmu)
    ke = ke.transpose(0, 1, 3, 2, 4).reshape(m, 144)  # (a, i, b, j) -> rows 3a+i, cols 3b+j
    return jax.ops.segment_sum(ke.reshape(-1), data.dense_index,
                               num_segments=n_dof * n_dof).reshape(n_dof, n_dof)


def log_pdet_schur(k, rigid_b):
    """The dense reference of ``(1/2) log pdet S``: of the dense stiffness ``k``
    ``(3N, 3N)`` (interior DOFs first) on its trailing ``3 n_b`` boundary DOFs, from one
    Cholesky factorisation of ``K + c P`` (``P = R_b R_b^T`` on the boundary block, ``R_b``
    orthonormal rigid modes, ``c`` the mean of ``diag K_bb``): its trailing block's factor is
    that of ``S + c P``, and ``det(S + c P) = c^6 pdet S``.  ``(3N)^3 / 3`` flops.

    Returns
    -------
    () array
        ``NaN`` when the factorisation fails (``K`` not positive definite on the complement
        of the rigid modes: non-positive parameters).
    """
    nb3 = rigid_b.shape[0]
    k_bb = k[-nb3:, -nb3:]
    c = jax.lax.stop_gradient(jnp.mean(jnp.diag(k_bb)))  # any c > 0: the result does not depend on it
    k = k.at[-nb3:, -nb3:].add(c * rigid_b @ rigid_b.T)
    chol = jnp.linalg.cholesky(0.5 * (k + k.T))
    return jnp.sum(jnp.log(jnp.diag(chol)[-nb3:])) - 3.0 * jnp.log(c)


def add_normaliser(logp, log_norm):
    """``logp + log_norm``, ``-inf`` where either is not finite (a failed factorisation gives
    a NaN normaliser: that position is rejected like any other hard-constraint violation)."""
    return jnp.where(jnp.isfinite(logp) & jnp.isfinite(log_norm), logp + log_norm, -jnp.inf)

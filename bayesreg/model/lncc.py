"""Local normalised cross-correlation (LNCC) as a similarity term, for image pairs whose
intensities differ by more than noise (a bias field, another contrast, another scanner).

ANTs' ``CC`` metric (Avants et al. 2008) compares ``f`` and the warped ``m`` in a
window around every voxel, and so is blind to an intensity change that is affine within a
window.  Here the windows are laid over the same quadrature points as the SSD term
(:mod:`bayesreg.model.similarity`): cubes of side ``window_mm`` centred on a regular grid of
spacing ``window_mm / 2`` (each point lies in up to eight windows, as ANTs' dense windows
overlap), holding the points whose *reference* positions lie inside.  A window ``k`` weighs
its points by their quadrature weights ``w_q`` normalised to ``a_kq`` (sum 1) and has weight
``W_k = sum_q w_q / 8`` (mm^3, so that ``sum_k W_k`` is about the brain's volume).

With ``f~ = f - mean_k f``, ``m~ = m - mean_k m`` (means weighted by ``a_kq``), ``s_f^2 =
var_k f + eps``, ``s_m^2 = var_k m + eps`` and ``rho_k = cov_k(f, m) / (s_f s_m)``, the term is
the sum of squares of the residuals

``r_kq = sqrt(W_k a_kq) (m~_q / s_m - rho_k f~_q / s_f)``,

``E = sum_k W_k (var_k m / s_m^2 - 2 rho_k^2 + rho_k^2 var_k f / s_f^2)``, which is
``sum_k W_k (1 - rho_k^2)`` as ``eps -> 0``: 0 where ``m`` is, window by window, an affine
function of ``f`` with positive or negative slope, and at most ``sum_k W_k``.  As a sum of
squares it has the Gauss-Newton curvature the Laplace proposal uses; ``eps`` (intensity^2)
keeps it smooth in flat windows.  The windows are fixed in the reference frame, so ``E`` is
as smooth in ``u`` as the interpolation of ``m``.

Units: ``E`` in mm^3 (dimensionless per unit volume); its temperature ``T_s`` in mm^3.

References
----------
B. B. Avants, C. L. Epstein, M. Grossman, J. C. Gee, "Symmetric diffeomorphic image
registration with cross-correlation", Medical Image Analysis 12 (2008) 26-41.
"""

from __future__ import annotations

from functools import partial
from typing import NamedTuple

import numpy as np
import scipy.sparse as sp
from scipy.spatial import cKDTree

import jax
import jax.numpy as jnp

from bayesreg.data.images import Image
from bayesreg.model.similarity import SSDTerm, build_ssd, moving_jacobian, moving_values

__all__ = ["LNCCTerm", "build_lncc", "lncc_windows", "lncc_residuals", "lncc", "lncc_gram"]

#: windows with fewer quadrature points than this are dropped (a correlation of two or three
#: values is all noise)
MIN_WINDOW_POINTS = 8

#: each point lies in at most this many windows (cubes of side ``window_mm`` every
#: ``window_mm / 2``; fewer near the brain's edge, where thin windows are dropped)
OVERLAP = 8


class LNCCTerm(NamedTuple):
    """Static data of the LNCC term: the quadrature and images of an SSD term, and windows
    as a flat list of (window, point) pairs, sorted by window.

    Attributes
    ----------
    quad : SSDTerm
        The quadrature points, ``f`` at them and the moving image
        (:func:`bayesreg.model.similarity.build_ssd`); its weights are not used.
    window : (P,) int
        The window of each pair (sorted, ``0 .. K-1``).
    point : (P,) int
        Its point: a flat index into the ``(M * Q,)`` quadrature points.
    a : (P,)
        The point's weight in its window (sums to 1 over a window).
    sqrt_w : (K,)
        ``sqrt(W_k)``, mm^1.5.
    f_hat : (P,)
        ``f~ / s_f`` of each pair (fixed).
    eps : ()
        Variance floor, intensity^2.
    """

    quad: SSDTerm
    window: jax.Array
    point: jax.Array
    a: jax.Array
    sqrt_w: jax.Array
    f_hat: jax.Array
    eps: jax.Array

    kind = "lncc"

    def residuals(self, u_e):
        """``r_kq`` ``(P,)`` (module docstring) for element displacements ``u_e`` ``(M, 4, 3)``."""
        return lncc_residuals(self, u_e)

    def energy(self, u_e):
        """``E = sum r_kq^2`` ``()``, mm^3."""
        r = lncc_residuals(self, u_e)
        return jnp.sum(r * r)

    def gram(self, u, tets, n_nodes: int):
        """:func:`lncc_gram` ``(3N, 3N)``."""
        return lncc_gram(self, u, tets, n_nodes)

    @property
    def n_observations(self) -> int:
        return int(np.size(self.quad.f_q))


def lncc_windows(points, weights, window_mm: float, *, min_points: int = MIN_WINDOW_POINTS):
    """The windows of :class:`LNCCTerm` over reference points.

    Parameters
    ----------
    points : (P, 3) array_like
        Reference (undeformed) positions of the quadrature points, world mm.
    weights : (P,) array_like
        Their quadrature weights (mm^3).
    window_mm : float
        Side of a window's cube, mm (> 0).
    min_points : int
        Windows with fewer points are dropped.

    Returns
    -------
    window, point : (S,) int ndarray
        The (window, point) pairs, sorted by window (``0 .. K-1``).
    a : (S,) ndarray
        Each point's weight within its window (sums to 1 over a window).
    w : (K,) ndarray
        Window weights ``W_k = sum w_q / 8``, mm^3.

    Raises
    ------
    ValueError
        ``window_mm`` not finite and positive, or no window holds ``min_points`` points.
    """
    if not (np.isfinite(window_mm) and window_mm > 0):
        raise ValueError(f"the LNCC window must be finite and > 0 mm, got {window_mm}")
    pts = np.asarray(points, np.float64).reshape(-1, 3)
    wq = np.asarray(weights, np.float64).ravel()
    step = window_mm / 2.0
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    axes = [np.arange(a, b + step, step) for a, b in zip(lo, hi)]
    centres = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    # Chebyshev ball of radius window/2: the cube; the tiny shrink keeps a point on a shared
    # face in the windows on both sides exactly as often as its neighbours
    members = cKDTree(pts).query_ball_point(centres, r=step * (1 - 1e-12), p=np.inf)
    members = [np.sort(np.asarray(m, np.int64)) for m in members if len(m) >= min_points]
    if not members:
        raise ValueError(f"no LNCC window of {window_mm} mm holds {min_points} quadrature points: "
                         "the window is too small for the quadrature (raise model.lncc.window_mm "
                         "or model.quadrature_level)")
    sizes = np.array([len(m) for m in members])
    window = np.repeat(np.arange(len(members)), sizes)
    point = np.concatenate(members)
    totals = np.array([wq[m].sum() for m in members])
    return window, point, wq[point] / totals[window], totals / OVERLAP


def build_lncc(nodes, tets, f: Image, m: Image, *, window_mm: float = 9.0, eps: float = 1e-4,
               cval=0.0, quadrature_level: int = 1, reach: Image | None = None,
               moving_dtype: str = "float64", interpolation: str = "linear") -> LNCCTerm:
    """Precompute :class:`LNCCTerm` for a mesh and an image pair.

    Parameters
    ----------
    nodes : (N, 3) array_like
        World mm.
    tets : (M, 4) array_like of int
    f, m : Image
        Pre- and intra-operative images (world frames must agree; intensities need not).
    window_mm : float
        Side of the windows' cubes, mm (ANTs' radius ``r`` voxels of spacing ``h``:
        ``(2 r + 1) h``).
    eps : float
        Variance floor (intensity^2, > 0).
    cval, quadrature_level, reach, moving_dtype, interpolation
        As :func:`bayesreg.model.similarity.build_ssd`.

    Raises
    ------
    ValueError
        As :func:`~bayesreg.model.similarity.build_ssd` and :func:`lncc_windows`, or ``eps``
        not finite and positive.

    Examples
    --------
    >>> import numpy as np
    >>> from bayesreg.data.images import Image
    >>> from bayesreg.mesh.tetmesh import box_mesh
    >>> from bayesreg.model.lncc import build_lncc
    >>> mesh = box_mesh((4, 4, 4), (30.0, 30.0, 30.0))
    >>> x = np.indices((40, 40, 40)).astype(float)
    >>> f = Image(np.sin(x[0] / 3) + np.cos(x[1] / 4) + x[2] / 20, np.eye(4))
    >>> m = Image(2.0 - 0.5 * f.data, np.eye(4))  # another contrast: E ~ 0 at u = 0
    >>> term = build_lncc(mesh.nodes, mesh.tets, f, m, window_mm=10.0)
    >>> float(term.energy(np.zeros((len(mesh.tets), 4, 3)))) < 1e-2
    True
    """
    if not (np.isfinite(eps) and eps > 0):
        raise ValueError(f"the LNCC variance floor eps must be finite and > 0, got {eps}")
    quad = build_ssd(nodes, tets, f, m, cval=cval, quadrature_level=quadrature_level, reach=reach,
                     moving_dtype=moving_dtype, interpolation=interpolation)
    pts = np.asarray(quad.points).reshape(-1, 3)
    wq = np.asarray(quad.sqrt_w).ravel() ** 2
    window, point, a, w = lncc_windows(pts, wq, window_mm)
    window, a = jnp.asarray(window, jnp.int32), jnp.asarray(a)
    f_hat, _ = _standardise(window, a, jnp.asarray(quad.f_q).ravel()[point], float(eps), n_win=len(w))
    return LNCCTerm(quad=quad, window=window, point=jnp.asarray(point, jnp.int32), a=a,
                    sqrt_w=jnp.asarray(np.sqrt(w)), f_hat=f_hat, eps=jnp.asarray(float(eps)))


def _window_sum(window, values, n_win: int):
    return jax.ops.segment_sum(values, window, num_segments=n_win, indices_are_sorted=True)


@partial(jax.jit, static_argnames="n_win")
def _standardise(window, a, values, eps, *, n_win: int):
    """Each pair's value centred and scaled within its window: ``(v - mean_k v) / s_k`` ``(P,)``,
    and ``s_k = sqrt(var_k v + eps)`` per pair ``(P,)`` (means and variances weighted by
    ``a``).  The fixed image's ``f^`` (:func:`build_lncc`) and the moving image's ``m^``
    (:func:`lncc_residuals`, :func:`lncc_gram`) alike."""
    tilde = values - _window_sum(window, a * values, n_win)[window]
    s = jnp.sqrt(_window_sum(window, a * tilde * tilde, n_win) + eps)[window]
    return tilde / s, s


def _moving_standardised(term: LNCCTerm, u_e):
    """``(m^, s_m, rho)`` per pair ``(P,)`` at element displacements ``u_e`` ``(M, 4, 3)``."""
    n_win = term.sqrt_w.shape[0]
    mv = moving_values(term.quad, u_e).reshape(-1)[term.point]  # (P,)
    m_hat, s_m = _standardise(term.window, term.a, mv, term.eps, n_win=n_win)
    rho = _window_sum(term.window, term.a * term.f_hat * m_hat, n_win)[term.window]
    return m_hat, s_m, rho


def lncc_residuals(term: LNCCTerm, u_e):
    """The residuals ``r_kq`` ``(P,)`` of the LNCC term, one per (window, point) pair
    (module docstring).

    Parameters
    ----------
    term : LNCCTerm
    u_e : (M, 4, 3) array
        Displacements of each element's nodes, mm.
    """
    m_hat, _, rho = _moving_standardised(term, u_e)
    return (term.sqrt_w[term.window] * jnp.sqrt(term.a)) * (m_hat - rho * term.f_hat)


def lncc(term: LNCCTerm, u_e):
    """``E`` (mm^3) of the LNCC term for element displacements ``u_e`` ``(M, 4, 3)``."""
    return term.energy(u_e)


def lncc_gram(term: LNCCTerm, u, tets, n_nodes: int):
    """Gauss-Newton Gram matrix ``J^T J`` of :func:`lncc_residuals` with respect to the nodal
    displacements ``u`` ``(N, 3)`` mm: ``(3N, 3N)`` sparse (CSR).

    A window's residuals depend on its moving values ``m`` through ``J_k = diag(g) + U~
    V^T`` (``g = c / s_m``, ``c = sqrt(W_k a)``; ``U~ = g [1, m^ - rho f^, f^]`` and ``V =
    -[a, a m^, a f^]``, ``m^ = m~ / s_m``, ``f^ = f~ / s_f``), so ``J_k^T J_k = diag(g^2) +
    Y_k B_k Y_k^T`` with ``Y_k = [V, g U~]`` (6 columns) and ``B_k = [[U~^T U~, I], [I, 0]]``.
    With ``D = dm/du`` (:func:`bayesreg.model.similarity.moving_jacobian`) the Gram matrix is
    ``D^T diag(sum_k g^2) D + Z B Z^T``, ``Z = D^T Y``: sparse products, never the
    ``(P, 3N)`` Jacobian itself.
    """
    tets = np.asarray(tets)
    dm = moving_jacobian(term.quad, u, tets, n_nodes)  # (n_points, 3N)
    n_points = dm.shape[0]
    k, pt, a = np.asarray(term.window), np.asarray(term.point), np.asarray(term.a)
    n_win = len(np.asarray(term.sqrt_w))

    def wsum(v):
        return np.bincount(k, weights=v, minlength=n_win)

    m_hat, s_m, rho = (np.asarray(v) for v in jax.jit(_moving_standardised)(
        term, jnp.asarray(u)[jnp.asarray(tets)]))
    f_hat = np.asarray(term.f_hat)
    g = np.asarray(term.sqrt_w)[k] * np.sqrt(a) / s_m  # (S,)
    u_t = g[:, None] * np.stack([np.ones_like(a), m_hat - rho * f_hat, f_hat], axis=-1)
    v = -np.stack([a, a * m_hat, a * f_hat], axis=-1)
    y = np.concatenate([v, g[:, None] * u_t], axis=-1)  # (S, 6)
    b = np.zeros((n_win, 6, 6))
    for i in range(3):
        for j in range(3):
            b[:, i, j] = wsum(u_t[:, i] * u_t[:, j])
    b[:, :3, 3:] = b[:, 3:, :3] = np.eye(3)
    ymat = sp.csr_array((y.ravel(), (np.repeat(pt, 6), (6 * k[:, None] + np.arange(6)).ravel())),
                        shape=(n_points, 6 * n_win))
    blocks = 6 * np.arange(n_win)[:, None, None]
    bmat = sp.csr_array((b.ravel(), (np.broadcast_to(blocks + np.arange(6)[None, :, None], b.shape).ravel(),
                                     np.broadcast_to(blocks + np.arange(6)[None, None, :], b.shape).ravel())),
                        shape=(6 * n_win, 6 * n_win))
    z = (dm.T @ ymat).tocsr()
    diag = np.bincount(pt, weights=g**2, minlength=n_points)
    gram = dm.T @ sp.diags_array(diag) @ dm + z @ bmat @ z.T
    return sp.csr_array(0.5 * (gram + gram.T))

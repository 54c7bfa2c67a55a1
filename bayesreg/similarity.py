"""SSD similarity ``E_s`` (paper Eq. 1) by 4-point Gauss quadrature on every tetrahedron.

``E_s(u) = sum_e sum_q w_eq (f(x_eq) - m(x_eq + u(x_eq)))^2`` with the degree-2 exact
4-point rule (Zienkiewicz & Taylor, ref. [11] of the paper): barycentric points
``(a, b, b, b)`` and permutations, ``a = (5 + 3 sqrt 5) / 20``, ``b = (5 - sqrt 5) / 20``,
weights ``V_e / 4``.  ``u(x_eq)`` is the FE interpolant of the nodal displacements;
``m`` is sampled by trilinear interpolation in world coordinates through its affine and
takes the value ``cval`` (default 0, background) outside its grid.

Units: intensities as given (the pipeline scales them to about [0, 1]), volumes in mm^3,
so ``E_s`` is in ``intensity^2 mm^3``.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from bayesreg import _xla

_xla.configure()
import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402

from bayesreg.images import Image, interpolate  # noqa: E402
from bayesreg.mesh import signed_volumes  # noqa: E402

__all__ = ["GAUSS_BARY", "gauss_points", "SSDTerm", "build_ssd", "ssd_residuals", "ssd"]

_A = (5.0 + 3.0 * np.sqrt(5.0)) / 20.0
_B = (5.0 - np.sqrt(5.0)) / 20.0
GAUSS_BARY = np.full((4, 4), _B) + np.eye(4) * (_A - _B)
"""Barycentric coordinates of the 4 Gauss points, ``(4 points, 4 nodes)``."""


def gauss_points(nodes, tets):
    """World coordinates ``(M, 4, 3)`` and weights ``(M, 4)`` (mm^3) of the Gauss points."""
    x = np.asarray(nodes, dtype=np.float64)[np.asarray(tets)]
    pts = np.einsum("qa,mad->mqd", GAUSS_BARY, x)
    vol = np.abs(signed_volumes(nodes, tets))
    return pts, np.repeat(vol[:, None] / 4.0, 4, axis=1)


class SSDTerm(NamedTuple):
    """Static data of ``E_s``: fixed image values at Gauss points and the moving image.

    Attributes
    ----------
    points : (M, 4, 3)
        Gauss points in the undeformed mesh, world mm.
    sqrt_w : (M, 4)
        Square roots of the quadrature weights (mm^1.5).
    f_q : (M, 4)
        Pre-operative image ``f`` at the Gauss points.
    m : (I, J, K)
        Intra-operative image.
    m_inv_affine : (4, 4)
        World-to-voxel matrix of ``m``.
    cval : ()
        Value of ``m`` outside its grid.
    """

    points: jax.Array
    sqrt_w: jax.Array
    f_q: jax.Array
    m: jax.Array
    m_inv_affine: jax.Array
    cval: jax.Array


def build_ssd(nodes, tets, f: Image, m: Image, *, cval=0.0) -> SSDTerm:
    """Precompute :class:`SSDTerm` for a mesh and an image pair (world frames must agree)."""
    pts, w = gauss_points(nodes, tets)
    f_inv = jnp.asarray(np.linalg.inv(f.affine))
    f_q = interpolate(jnp.asarray(f.data, dtype=jnp.float64), f_inv, jnp.asarray(pts), cval)
    return SSDTerm(
        points=jnp.asarray(pts),
        sqrt_w=jnp.sqrt(jnp.asarray(w)),
        f_q=f_q,
        m=jnp.asarray(m.data, dtype=jnp.float64),
        m_inv_affine=jnp.asarray(np.linalg.inv(m.affine)),
        cval=jnp.asarray(float(cval)),
    )


def ssd_residuals(term: SSDTerm, u_e):
    """Weighted residuals ``sqrt(w_q) (f(x_q) - m(x_q + u(x_q)))``, ``(M, 4)``.

    Parameters
    ----------
    term : SSDTerm
    u_e : (M, 4, 3) array
        Displacements of each element's nodes, mm.
    """
    # explicit multiply-and-sum: einsum over gathered values is slower on XLA:CPU
    u_q = jnp.sum(jnp.asarray(GAUSS_BARY)[None, :, :, None] * u_e[:, None, :, :], axis=2)
    m_q = interpolate(term.m, term.m_inv_affine, term.points + u_q, term.cval)
    return term.sqrt_w * (term.f_q - m_q)


def ssd(term: SSDTerm, u_e):
    """``E_s`` (paper Eq. 1) for element displacements ``u_e`` ``(M, 4, 3)``."""
    r = ssd_residuals(term, u_e)
    return jnp.sum(r * r)

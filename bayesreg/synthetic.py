"""Synthetic brain shift with a known truth (paper Sec. 4.1).

* :func:`brain_shift` - boundary nodes at the top of the brain pushed toward the brain's
  centre of gravity (a supine craniotomy), the push fading smoothly over the surrounding
  boundary; interior nodes from the FE solve with known ``lam``, ``mu``.
* :func:`bayesreg.contact.constrained_shift` - the paper's own truth: the other boundary
  nodes at the minimum of the elastic energy under the skull constraint.

The intra-operative image of a synthetic case is ``f`` warped through the truth's FE map
(:func:`bayesreg.warp.warp_image`).  Units: world mm.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from bayesreg.fem import stiffness_matrix
from bayesreg.mesh import Mesh, signed_volumes

__all__ = ["Truth", "brain_shift", "solve_dirichlet", "centre_of_gravity", "top_boundary"]


class Truth(NamedTuple):
    """Known deformation of a synthetic case.

    Attributes
    ----------
    u : (N, 3)
        nodal displacements, mm
    lam_e, mu_e : (M,)
        per-element Lamé parameters used
    pushed : (P,) int
        nodes given the full push (Dirichlet)
    """

    u: np.ndarray
    lam_e: np.ndarray
    mu_e: np.ndarray
    pushed: np.ndarray


def solve_dirichlet(mesh: Mesh, lam_e, mu_e, fixed, u_fixed):
    """Direct (SciPy) solve of ``K u = 0`` with ``u[fixed] = u_fixed``; returns ``(N, 3)``."""
    k = stiffness_matrix(mesh.nodes, mesh.tets, lam_e, mu_e)
    n = len(mesh.nodes)
    is_f = np.zeros(n, bool)
    is_f[fixed] = True
    fd = (3 * np.flatnonzero(is_f)[:, None] + np.arange(3)).ravel()
    fr = (3 * np.flatnonzero(~is_f)[:, None] + np.arange(3)).ravel()
    u = np.zeros(3 * n)
    u[fd] = np.asarray(u_fixed, dtype=np.float64).ravel()
    u[fr] = spla.spsolve(sp.csc_matrix(k[fr][:, fr]), -(k[fr][:, fd] @ u[fd]))
    return u.reshape(n, 3)


def centre_of_gravity(mesh: Mesh) -> np.ndarray:
    """Volume-weighted centroid of the mesh, ``(3,)`` world mm."""
    vol = np.abs(signed_volumes(mesh.nodes, mesh.tets))
    return (vol[:, None] * mesh.nodes[mesh.tets].mean(axis=1)).sum(0) / vol.sum()


def top_boundary(mesh: Mesh, n_pushed) -> np.ndarray:
    """Positions in ``mesh.boundary`` of the ``n_pushed`` boundary nodes of largest world z."""
    nb = len(mesh.boundary)
    if not 1 <= n_pushed <= nb:
        raise ValueError(f"n_pushed must lie in [1, {nb}], got {n_pushed}")
    return np.argsort(-mesh.nodes[mesh.boundary][:, 2])[:n_pushed]


def brain_shift(mesh: Mesh, lam_e, mu_e, *, shift_mm=10.0, n_pushed=20, falloff_mm=30.0) -> Truth:
    """Synthetic brain shift toward the centre of gravity.

    The ``n_pushed`` boundary nodes with the largest world ``z`` (superior) move
    ``shift_mm`` toward the volume-weighted centroid of the mesh.  Every other boundary
    node ``p`` moves toward the centroid by ``shift_mm * exp(-d^2 / (2 falloff_mm^2))``,
    ``d`` its distance to the nearest pushed node; interior nodes solve ``K u = 0``.

    Raises
    ------
    ValueError
        Non-positive ``shift_mm``/``falloff_mm`` or ``n_pushed`` outside ``[1, n_b]``.
    """
    if shift_mm <= 0 or falloff_mm <= 0:
        raise ValueError("shift_mm and falloff_mm must be > 0")
    cog = centre_of_gravity(mesh)
    pb = mesh.nodes[mesh.boundary]
    pushed_local = top_boundary(mesh, n_pushed)
    d = np.min(np.linalg.norm(pb[:, None, :] - pb[None, pushed_local, :], axis=2), axis=1)
    weight = np.exp(-0.5 * (d / falloff_mm) ** 2)
    weight[pushed_local] = 1.0
    direction = cog - pb
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    u_b = shift_mm * weight[:, None] * direction
    u = solve_dirichlet(mesh, lam_e, mu_e, mesh.boundary, u_b)
    return Truth(u, np.asarray(lam_e, float), np.asarray(mu_e, float), mesh.boundary[pushed_local])


# ----------------------------------------------------------------------------------------
# Ground truth of paper Sec. 4.1: energy minimiser under the skull constraint
# ----------------------------------------------------------------------------------------



"""The skull: one smooth signed distance for the truth, the mode search and the sampler.

The forbidden region (the skull, and everything outside the image grid) becomes a smooth
signed distance ``d(x)`` in world mm, ``d > 0`` inside it (:func:`skull_constraint`): the
Euclidean distance transform between voxel centres of the two classes, shifted by half a
voxel so that ``d = 0`` on the voxel faces that separate them (where the nearest-voxel
rule puts the wall), evaluated as a uniform cubic B-spline with these samples as its
coefficients (a quasi-interpolant: C2, and it reproduces linear functions, so a
face-aligned wall stays exact while the staircase's corners are rounded).  Allowed voxels
not connected to the mesh at rest (given ``nodes``) count as forbidden: a node cannot pass
through the skull into a pocket beyond it.

* The hard constraint (paper Sec. 3.2) is its sign: a point with ``d >= 0`` is forbidden
  (:func:`points_forbidden`), ``log p = -inf``.
* The optional barrier of width ``w`` (:func:`skull_barrier`) is a smooth function of the
  clearance ``-d``: ``-(w / (-d) - 1)^3`` for ``0 < -d < w``, 0 beyond (C2), ``-> -inf`` at
  the wall, so that gradient trajectories turn before it.
* The paper's constrained truth (:mod:`bayesreg.truth.contact`) is made against the same ``d``
  (:class:`SignedDistance`: the same spline in NumPy with its gradient and Hessian), and
  the mode search sees it too: no stage sees a voxel staircase another does not.

All distances are in world mm; the grid carries its affine.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import scipy.ndimage as ndi

from bayesreg.data.interpolation import CUBIC_PAD, cubic_clamped

__all__ = ["SkullConstraint", "skull_constraint", "with_barrier", "points_forbidden",
           "skull_distance", "skull_barrier", "SignedDistance", "BARRIER_FLOOR", "GRID_PAD",
           "element_volumes", "inversion_barrier"]

#: Forbidden voxels added around the grid: outside the image grid is forbidden, and ``d``
#: keeps growing there for a few voxels (then it is held).
GRID_PAD = 5


class SkullConstraint(NamedTuple):
    """The forbidden region as a smooth signed distance, and the barrier in front of it.

    Attributes
    ----------
    coef : (I + 2 GRID_PAD + 6, ...)
        Cubic B-spline coefficients of ``d`` (mm): the signed distance samples of the grid
        padded by :data:`GRID_PAD` forbidden voxels, themselves padded for
        :func:`bayesreg.data.interpolation.cubic_clamped`.
    inv_affine : (4, 4)
        World mm to the voxel coordinates of the padded grid (the image's own plus
        :data:`GRID_PAD`).
    barrier_width : ()
        Width ``w`` (mm) of the barrier, 0 = off.
    barrier_wall : () bool
        Whether points at the barrier's own singularity are forbidden
        (:func:`skull_barrier`'s ``clear``): true for sampling; the mode search turns it off,
        so that its line search meets the barrier's huge finite values there and steps back.
    """

    coef: jax.Array
    inv_affine: jax.Array
    barrier_width: jax.Array
    barrier_wall: jax.Array = True


def _admissible(mask: np.ndarray, inv_affine: np.ndarray, nodes) -> np.ndarray:
    """The allowed voxels 6-connected to those that hold ``nodes`` (at rest)."""
    comp, _ = ndi.label(~mask)
    idx = np.floor(np.asarray(nodes, np.float64) @ inv_affine[:3, :3].T + inv_affine[:3, 3] + 0.5)
    idx = idx.astype(np.int64)
    ok = np.all((idx >= 0) & (idx < np.array(mask.shape)), axis=1)
    seeds = np.unique(comp[tuple(idx[ok].T)])
    return np.isin(comp, seeds[seeds > 0])


def skull_constraint(forbidden, *, barrier_mm: float = 0.0, nodes=None) -> SkullConstraint:
    """The constraint of a forbidden-region image (``data > 0`` is forbidden).

    Parameters
    ----------
    forbidden : Image
        3D image with a finite invertible affine.
    barrier_mm : float
        Width of the barrier (:func:`with_barrier`), mm; 0 = off.
    nodes : (N, 3) array, optional
        The mesh at rest, world mm: allowed voxels not 6-connected to those holding a node
        are forbidden too.

    Raises
    ------
    ValueError
        Through :func:`with_barrier`: a negative or non-finite width.
    """
    affine = np.asarray(forbidden.affine, dtype=np.float64)
    inv = np.linalg.inv(affine)
    mask = np.asarray(forbidden.data) > 0
    if nodes is not None:
        mask = ~_admissible(mask, inv, nodes)
    spacing = np.linalg.norm(affine[:3, :3], axis=0)
    f = np.pad(mask, GRID_PAD, constant_values=True)
    half = 0.5 * spacing.min()
    inside = ndi.distance_transform_edt(f, sampling=spacing)
    outside = ndi.distance_transform_edt(~f, sampling=spacing)
    grid = np.where(f, inside - half, -(outside - half))
    shift = np.eye(4)
    shift[:3, 3] = GRID_PAD
    skull = SkullConstraint(
        coef=jnp.asarray(np.pad(grid, CUBIC_PAD, mode="edge")),
        inv_affine=jnp.asarray(shift @ inv),
        barrier_width=jnp.asarray(0.0),
        barrier_wall=jnp.asarray(True),
    )
    return with_barrier(skull, barrier_mm)


def with_barrier(skull: SkullConstraint, barrier_mm: float) -> SkullConstraint:
    """``skull`` with a barrier of width ``barrier_mm`` (mm; 0 = off) in place of its own.

    Raises
    ------
    ValueError
        ``barrier_mm`` negative or not finite.
    """
    if not (barrier_mm >= 0 and np.isfinite(barrier_mm)):
        raise ValueError(f"the skull barrier width must be finite and >= 0 mm, got {barrier_mm}")
    return skull._replace(barrier_width=jnp.asarray(float(barrier_mm)))


@jax.jit  # (also called from host code: one program, not ~50 eager ops of ~30 ms)
def skull_distance(skull: SkullConstraint, points):
    """The smooth signed distance ``d`` (mm, ``> 0`` inside the forbidden region) at world
    points ``(..., 3)`` mm (module docstring); differentiable (C2).

    Returns
    -------
    (...,) array
    """
    a = skull.inv_affine
    return cubic_clamped(skull.coef, points @ a[:3, :3].T + a[:3, 3])


@jax.jit
def points_forbidden(skull: SkullConstraint, points):
    """Whether each world point ``(..., 3)`` mm breaks the hard constraint: ``d >= 0``
    (in the skull, outside the image grid, or in a pocket beyond the skull).

    Returns
    -------
    (...) bool array
    """
    return skull_distance(skull, points) >= 0.0


BARRIER_FLOOR = 1e-6
"""Fraction of the barrier's width below which :func:`skull_barrier` stops following its
formula and forbids (the barrier's own wall)."""


def skull_barrier(skull: SkullConstraint, points):
    """Smooth barrier against the skull: ``-sum (w / s - 1)^3`` over the points with
    clearance ``0 < s < w`` (``s = -d``, :func:`skull_distance`; ``w = barrier_width``), 0
    beyond ``w`` (C2 there), ``-> -inf`` as ``s -> 0``; and whether every point is clear of
    the barrier's own wall, ``s > BARRIER_FLOOR * w``.

    An optional change of the model (``model.skull_barrier_mm``; 0 = off, the paper's hard
    constraint alone): it bends the log-density down within ``w`` of the skull so that
    gradient trajectories turn before they reach the hard ``-inf`` wall, which stays in
    place.  The barrier and the wall are one surface, ``d = 0`` (the posterior forbids a
    point not clear of the floor, which would otherwise sit on a flat, clamped plateau).

    Parameters
    ----------
    skull : SkullConstraint
    points : (P, 3) array
        Deformed node positions, world mm.

    Returns
    -------
    barrier : () array
    clear : () bool array
        True also where the barrier or its wall (:attr:`SkullConstraint.barrier_wall`) is
        off.
    """
    w = skull.barrier_width
    s = -skull_distance(skull, points)
    near = s < w
    floor = BARRIER_FLOOR * jnp.maximum(w, 1e-12)
    s_safe = jnp.where(near, jnp.maximum(s, floor), 1.0)
    clear = jnp.all(s > floor) | ~jnp.asarray(skull.barrier_wall) | ~(w > 0)
    value = -jnp.sum(jnp.where(near, (w / s_safe - 1.0) ** 3, 0.0))
    return jnp.where(w > 0, value, 0.0), clear


def element_volumes(points, tets):
    """Signed element volumes ``(M,)``, mm^3, of world points ``(N, 3)`` mm and ``tets``
    ``(M, 4)``, traceable by JAX (:func:`bayesreg.mesh.tetmesh.signed_volumes` is its NumPy form):
    positive for the mesh's orientation, ``<= 0`` for an inverted (or flat) element, the
    other hard constraint (paper Sec. 3.2)."""
    x = points[tets]
    return jnp.einsum("mi,mi->m", jnp.cross(x[:, 1] - x[:, 0], x[:, 2] - x[:, 0]),
                      x[:, 3] - x[:, 0]) / 6.0


def inversion_barrier(points, tets, volumes0, ratio: float):
    """Smooth barrier against inverted elements: ``-sum (r / J - 1)^3`` over the elements
    whose volume ratio ``J = V / V_0`` is below ``r = ratio``, 0 elsewhere (C2 at ``J = r``),
    ``-> -inf`` as ``J -> 0``.

    Not part of the model (whose constraint is the hard ``J > 0``): the mode search
    (:func:`bayesreg.inference.mode.find_mode`) adds it, so that its steps turn before an element
    collapses instead of stalling on a sliver whose gradient points through the wall.

    Parameters
    ----------
    points : (N, 3) array
        Deformed nodes, world mm.
    tets : (M, 4) int array
    volumes0 : (M,) array
        :func:`element_volumes` at rest (> 0), mm^3.
    ratio : float
        ``r`` in (0, 1).

    Returns
    -------
    () array
        ``0`` when no element is below ``r``; elements with ``J <= 0`` contribute a finite
        value (the hard constraint rejects them).
    """
    j = element_volumes(points, tets) / volumes0
    near = j < ratio
    j_safe = jnp.where(near, jnp.maximum(j, 1e-12 * ratio), 1.0)
    return -jnp.sum(jnp.where(near, (ratio / j_safe - 1.0) ** 3, 0.0))


class SignedDistance:
    """:func:`skull_distance` on the host (NumPy) with its gradient and Hessian, for the
    Newton solver of the constrained truth (:mod:`bayesreg.truth.contact`): the same spline, the
    same coefficients, the same clamping.

    Parameters
    ----------
    skull : SkullConstraint
    """

    def __init__(self, skull: SkullConstraint):
        self.coef = np.asarray(skull.coef)
        self.inv = np.asarray(skull.inv_affine)
        self.hi = np.array(self.coef.shape) - 2 * CUBIC_PAD - 1.0

    @staticmethod
    def _bspline(t):
        s = 1.0 - t
        w = np.stack([s**3, 3 * t**3 - 6 * t**2 + 4, -3 * t**3 + 3 * t**2 + 3 * t + 1, t**3], -1)
        dw = np.stack([-3 * s**2, 9 * t**2 - 12 * t, -9 * t**2 + 6 * t + 3, 3 * t**2], -1)
        d2w = np.stack([s, 3 * t - 2, 1 - 3 * t, t], -1)
        return w / 6.0, dw / 6.0, d2w

    def __call__(self, points, hessian=False):
        """``d`` ``(P,)``, ``grad d`` ``(P, 3)`` and, with ``hessian``, ``grad grad d``
        ``(P, 3, 3)`` at world points ``(P, 3)`` mm (zero derivatives across a clamped
        coordinate)."""
        points = np.asarray(points, np.float64)
        c = points @ self.inv[:3, :3].T + self.inv[:3, 3]
        cc = np.clip(c, 0.0, self.hi) + CUBIC_PAD
        i0 = np.floor(cc).astype(np.int64)
        t = cc - i0
        taps = i0[:, :, None] + np.arange(-1, 3)  # (P, 3, 4)
        v = self.coef[taps[:, 0, :, None, None], taps[:, 1, None, :, None], taps[:, 2, None, None, :]]
        w, dw, d2w = [np.moveaxis(a, 1, 0) for a in self._bspline(t)]  # each (3, P, 4)

        def contract(kx, ky, kz):
            return np.einsum("pa,pb,pc,pabc->p", kx[0], ky[1], kz[2], v)

        val = contract(w, w, w)
        keep = (c >= 0.0) & (c <= self.hi)  # not clamped
        gc = np.stack([contract(dw, w, w), contract(w, dw, w), contract(w, w, dw)], -1) * keep
        grad = gc @ self.inv[:3, :3]
        if not hessian:
            return val, grad
        hc = np.empty((len(points), 3, 3))
        for a in range(3):
            for b in range(a, 3):
                k = [w, w, w]
                if a == b:
                    k[a] = d2w
                else:
                    k[a], k[b] = dw, dw
                hc[:, a, b] = hc[:, b, a] = contract(*k)
        hc *= keep[:, :, None] & keep[:, None, :]
        return val, grad, np.einsum("ai,pab,bj->pij", self.inv[:3, :3], hc, self.inv[:3, :3])

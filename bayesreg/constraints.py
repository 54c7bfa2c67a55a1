"""The skull as a hard constraint, and the optional smooth barrier in front of it (Sec. 3.2).

A node that ends in the forbidden (skull) region, or outside the image grid, makes the
log-density ``-inf``.  The rule is the nearest voxel's label (:func:`points_forbidden`,
SciPy's order-0 interpolation).  An optional barrier of width ``w``
(:func:`skull_barrier`) bends the log-density down within ``w`` of the forbidden voxel
cubes so that gradient trajectories turn before they reach the wall, which stays in place:
no stored draw can violate the constraint.

All distances are in world mm; the forbidden region lives on a voxel grid with its affine.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

__all__ = ["SkullConstraint", "skull_constraint", "with_barrier", "points_forbidden",
           "skull_distance", "skull_barrier", "BARRIER_FLOOR"]


class SkullConstraint(NamedTuple):
    """The forbidden region and the barrier in front of it (a pytree of arrays).

    Attributes
    ----------
    forbidden : (I, J, K) bool
        Forbidden voxels (the skull) on the label grid.
    inv_affine : (4, 4)
        World-to-voxel matrix of that grid.
    voxel_size : (3,)
        Spacing of the grid, mm (the column norms of its affine).
    barrier_offsets : (K, 3) int
        Voxel offsets around a point's nearest voxel whose cubes the barrier looks at
        (``{-R..R}^3``, ``R = max(1, ceil(w / min voxel_size))``: every cube nearer than
        ``w``; ``(0, 3)`` when the barrier is off).
    barrier_width : ()
        Width ``w`` (mm) of the barrier, 0 = off.
    barrier_wall : () bool
        Whether points at the barrier's own singularity are forbidden
        (:func:`skull_barrier`'s ``clear``): true for sampling; the mode search turns it off, so that
        its line search meets the barrier's huge finite values there and steps back.
    """

    forbidden: jax.Array
    inv_affine: jax.Array
    voxel_size: jax.Array
    barrier_offsets: jax.Array
    barrier_width: jax.Array
    barrier_wall: jax.Array = True


def skull_constraint(forbidden, *, barrier_mm: float = 0.0) -> SkullConstraint:
    """The constraint of a forbidden-region image (``data > 0`` is forbidden).

    Parameters
    ----------
    forbidden : Image
        3D image with a finite invertible affine.
    barrier_mm : float
        Width of the barrier (:func:`with_barrier`), mm; 0 = off.

    Raises
    ------
    ValueError
        Through :func:`with_barrier`: a negative or non-finite width.
    """
    affine = np.asarray(forbidden.affine, dtype=np.float64)
    spacing = np.linalg.norm(affine[:3, :3], axis=0)
    skull = SkullConstraint(
        forbidden=jnp.asarray(np.asarray(forbidden.data) > 0),
        inv_affine=jnp.asarray(np.linalg.inv(affine)),
        voxel_size=jnp.asarray(spacing),
        barrier_offsets=jnp.zeros((0, 3), dtype=jnp.int32),
        barrier_width=jnp.asarray(0.0),
        barrier_wall=jnp.asarray(True),
    )
    return with_barrier(skull, barrier_mm)


def with_barrier(skull: SkullConstraint, barrier_mm: float) -> SkullConstraint:
    """``skull`` with a barrier of width ``barrier_mm`` (mm; 0 = off) in place of its own:
    sets :attr:`SkullConstraint.barrier_width` and the voxel offsets searched,
    ``{-R..R}^3`` with ``R = max(1, ceil(w / min voxel_size))`` (a cube at offset ``k`` is at
    least ``(k - 1) h`` away, so every cube nearer than ``w`` is searched).

    Raises
    ------
    ValueError
        ``barrier_mm`` negative or not finite.
    """
    if not (barrier_mm >= 0 and np.isfinite(barrier_mm)):
        raise ValueError(f"the skull barrier width must be finite and >= 0 mm, got {barrier_mm}")
    offsets = np.zeros((0, 3), dtype=np.int32)
    if barrier_mm > 0:
        r = max(1, int(np.ceil(barrier_mm / float(np.min(np.asarray(skull.voxel_size))) - 1e-12)))
        rng = np.arange(-r, r + 1)
        offsets = np.stack(np.meshgrid(rng, rng, rng, indexing="ij"), -1).reshape(-1, 3)
    return skull._replace(barrier_offsets=jnp.asarray(offsets, dtype=jnp.int32),
                          barrier_width=jnp.asarray(float(barrier_mm)))


def _voxel_coordinates(skull: SkullConstraint, points):
    """Continuous voxel coordinates ``(..., 3)`` of world points on the forbidden grid."""
    return points @ skull.inv_affine[:3, :3].T + skull.inv_affine[:3, 3]


def _voxel_forbidden(skull: SkullConstraint, idx):
    """Whether the voxels ``idx`` ``(..., 3)`` int are forbidden (outside the grid counts)."""
    shape = jnp.array(skull.forbidden.shape)
    inside = jnp.all((idx >= 0) & (idx < shape), axis=-1)
    idc = jnp.clip(idx, 0, shape - 1)
    return ~inside | skull.forbidden[idc[..., 0], idc[..., 1], idc[..., 2]]


def points_forbidden(skull: SkullConstraint, points):
    """Whether each world point ``(..., 3)`` mm breaks the hard constraint: its nearest voxel
    is forbidden or outside the grid (the rule of SciPy's order-0 interpolation).

    Returns
    -------
    (...) bool array
    """
    idx = jnp.floor(_voxel_coordinates(skull, points) + 0.5).astype(jnp.int32)  # nearest voxel
    return _voxel_forbidden(skull, idx)


def skull_distance(skull: SkullConstraint, points):
    """Smoothed distance (mm) from each point to the forbidden region as the hard
    constraint sees it: the union of the cubes (voxel cells) of the forbidden voxels.

    ``d = -tau log sum_k exp(-d_k / tau)`` over the forbidden cubes ``k`` among the
    :attr:`SkullConstraint.barrier_offsets` around the point's nearest voxel (voxels
    outside the grid count as forbidden, as in the hard rule), ``d_k`` the Euclidean
    distance to cube ``k`` in mm, ``tau = w / 20``.  The soft minimum is C-infinity where
    the cubes' distances are (outside every cube) and never exceeds the true distance, so
    ``d <= 0`` whenever the nearest-voxel rule says "forbidden"; the cubes searched cover
    every cube nearer than ``w``.  Exact for an affine with orthogonal columns (cubes are
    boxes of :attr:`SkullConstraint.voxel_size`); approximate for an oblique one.

    Parameters
    ----------
    skull : SkullConstraint
        With ``barrier_width > 0``.
    points : (P, 3) array
        World mm.

    Returns
    -------
    (P,) array
        mm (``+inf`` where no forbidden cube is searched).
    """
    c = _voxel_coordinates(skull, points)
    v = jnp.floor(c + 0.5)  # nearest voxel (the hard rule's)
    cells = v[:, None, :] + skull.barrier_offsets  # (P, K, 3)
    gap = jnp.maximum(jnp.abs(c[:, None, :] - cells) - 0.5, 0.0) * skull.voxel_size
    s2 = jnp.sum(gap * gap, axis=-1)
    dist = jnp.where(s2 > 0, jnp.sqrt(jnp.where(s2 > 0, s2, 1.0)), 0.0)  # 0 inside the cube
    forb = _voxel_forbidden(skull, cells.astype(jnp.int32))
    tau = skull.barrier_width / 20.0
    z = jnp.where(forb, -dist / tau, -jnp.inf)
    return -tau * jax.nn.logsumexp(z, axis=-1)


BARRIER_FLOOR = 1e-6
"""Fraction of the barrier's width below which :func:`skull_barrier` stops following its
formula and forbids (the barrier's own wall)."""


def skull_barrier(skull: SkullConstraint, points):
    """Smooth barrier against the skull: ``-sum (w / d - 1)^2`` over the points with
    ``0 < d < w`` (``d`` = :func:`skull_distance`, ``w = barrier_width``), 0 beyond ``w``,
    ``-> -inf`` as ``d -> 0``; C1 in the points; and whether every point is clear of the
    barrier's own wall, ``d > BARRIER_FLOOR * w``.

    An optional change of the model (``model.skull_barrier_mm``; 0 = off, the paper's hard
    constraint alone): it bends the log-density down within ``w`` of the skull so that
    gradient trajectories turn before they reach the hard ``-inf`` wall, which stays in
    place.  ``d`` is the distance to the voxel cubes that the hard rule forbids, so the
    barrier's singularity is never behind the wall (a trilinearly interpolated signed
    distance would read clearance at the corners of the voxel staircase where the rule
    already forbids).

    ``d`` is a soft minimum, up to ``(w / 20) log 27`` below the true distance, so a point
    that the hard rule allows can have ``d <= 0``, where the barrier cannot follow its
    formula.  The posterior forbids points that are not clear as it forbids the skull
    (``log p = -inf``), so the barrier's singularity is the model's wall in front of the
    hard one (at most ``0.165 w`` in front of it): the log-density has no flat plateau
    there, which, clamped, held a chain at ``log p = -1e12`` with a zero gradient (a
    BrainWeb brain, one chain of three).  Below the floor the value is held finite.

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
    if skull.barrier_offsets.shape[0] == 0:
        return jnp.zeros(()), jnp.asarray(True)
    d = skull_distance(skull, points)
    near = d < w
    floor = BARRIER_FLOOR * jnp.maximum(w, 1e-12)
    d_safe = jnp.where(near, jnp.maximum(d, floor), 1.0)
    clear = jnp.all(d > floor) | ~jnp.asarray(skull.barrier_wall)
    return -jnp.sum(jnp.where(near, (w / d_safe - 1.0) ** 2, 0.0)), clear

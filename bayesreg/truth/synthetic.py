"""Synthetic brain shift with a known truth (paper Sec. 4.1), made by the model or not.

Truths the model makes (an FE field: interior nodes solve ``K u = 0`` with known ``lam``,
``mu``):

* :func:`brain_shift` - boundary nodes at the top of the brain pushed toward the brain's
  centre of gravity (a supine craniotomy), the push fading smoothly over the surrounding
  boundary.
* :func:`bayesreg.truth.contact.constrained_shift` - the paper's own truth: the other boundary
  nodes at the minimum of the elastic energy under the skull constraint.

Truths the model does not make (a dense voxel field: no ``lam``, ``mu`` reproduce it, the
case real brain shift poses):

* :func:`bump_field` - a smooth Gaussian bump of the whole image toward the centre of
  gravity, peaked at the top of the brain.
* a displacement field from a file (another registration's: ITK/ANTs or bayesreg's own),
  :func:`field_truth` samples it at the nodes.

Between the two, :func:`with_discrepancy` adds a dense field to an FE truth: known ``lam``,
``mu`` and a part no FE field makes (the model discrepancy of Kennedy and O'Hagan 2001),
so that the elastic parameters' intervals can be checked against their truths under mismatch.

The intra-operative image of a synthetic case is ``f`` warped through the truth's FE map
(:func:`bayesreg.mesh.warp.warp_image`) or through the dense field
(:func:`bayesreg.mesh.warp.warp_image_field`).  Units: world mm.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from bayesreg.fem.element import stiffness_matrix
from bayesreg.data.images import Image, grid_points
from bayesreg.mesh.tetmesh import Mesh, signed_volumes

__all__ = ["Truth", "brain_shift", "bump_field", "field_truth", "random_field",
           "with_discrepancy", "fe_field", "solve_dirichlet", "centre_of_gravity", "top_boundary"]


class Truth(NamedTuple):
    """Known deformation of a synthetic case.

    Attributes
    ----------
    u : (N, 3)
        nodal displacements, mm
    lam_e, mu_e : (M,) or None
        per-element Lamé parameters used (also of an FE truth with a field added,
        :func:`with_discrepancy`); ``None`` for a dense truth made without them
    pushed : (P,) int
        nodes given the full push (Dirichlet); for a dense field, the nodes nearest its peak
    field : Image or None
        the dense displacement field ``(I, J, K, 3)`` mm on ``f``'s grid of a truth the
        model did not make (``m(x + u(x)) = f(x)`` for every voxel centre ``x``); ``None``
        for an FE truth alone (its field is the FE interpolation of ``u``)
    """

    u: np.ndarray
    lam_e: np.ndarray | None
    mu_e: np.ndarray | None
    pushed: np.ndarray
    field: Image | None = None

    @property
    def made_by_model(self) -> bool:
        """Whether the truth is an FE field of known ``lam``, ``mu`` and nothing more (the
        model can make it)."""
        return self.lam_e is not None and self.field is None

    @property
    def parameters_known(self) -> bool:
        """Whether the truth carries the Lamé parameters of an FE field, alone or with a part
        the model did not make (:func:`with_discrepancy`): the ratios have truths."""
        return self.lam_e is not None


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


def bump_field(grid: Image, mesh: Mesh, *, shift_mm=8.0, n_pushed=20, radius_mm=30.0) -> Image:
    """A smooth Gaussian bump of the whole image toward the brain's centre of gravity.

    ``u(x) = shift_mm * exp(-|x - c|^2 / (2 radius_mm^2)) * d`` at every voxel centre ``x``
    of ``grid``: ``c`` the centroid of the ``n_pushed`` boundary nodes of largest world
    ``z`` (:func:`top_boundary`), ``d`` the unit vector from ``c`` to the mesh's centre of
    gravity (:func:`centre_of_gravity`).  The interior of the brain moves with the same
    Gaussian profile, which no linear-elastic FE field reproduces: the model's mismatch
    case.  The map ``x -> x + u(x)`` is invertible while
    ``shift_mm / radius_mm < e^(1/2) = 1.65`` (its largest gradient is
    ``shift_mm / radius_mm * e^(-1/2)``).

    Parameters
    ----------
    grid : Image
        The grid (``f``'s), world mm.
    mesh : Mesh
        Gives the bump's centre and direction.
    shift_mm, radius_mm : float
        Peak displacement and Gaussian sd, mm.
    n_pushed : int
        Top boundary nodes whose centroid is the peak.

    Returns
    -------
    Image
        ``(I, J, K, 3)`` float64 displacement in world mm, ``grid``'s affine.

    Raises
    ------
    ValueError
        Non-positive ``shift_mm`` or ``radius_mm``, ``shift_mm / radius_mm >= 1.6`` (the map
        folds), or ``n_pushed`` outside ``[1, n_b]``.
    """
    if shift_mm <= 0 or radius_mm <= 0:
        raise ValueError("shift_mm and radius_mm must be > 0")
    if shift_mm / radius_mm >= 1.6:
        raise ValueError(f"a bump of {shift_mm:g} mm with radius {radius_mm:g} mm folds the "
                         "image (shift / radius must stay below 1.6)")
    top = mesh.nodes[mesh.boundary][top_boundary(mesh, n_pushed)]
    centre = top.mean(axis=0)
    direction = centre_of_gravity(mesh) - centre
    direction /= np.linalg.norm(direction)
    pts = grid_points(grid)
    weight = np.exp(-0.5 * np.sum((pts - centre) ** 2, axis=1) / radius_mm**2)
    u = shift_mm * weight[:, None] * direction
    return Image(u.reshape(*grid.data.shape[:3], 3), grid.affine)


def random_field(grid: Image, mesh: Mesh, *, shift_mm=8.0, length_mm=30.0, seed=0,
                 solenoidal: bool = False) -> Image:
    """A smooth random displacement of the whole image: a mismatch no FE field makes.

    Each component is white noise convolved with a Gaussian of sd ``length_mm`` (a
    stationary Gaussian random field whose correlation is Gaussian of sd
    ``length_mm * sqrt(2)``), drawn on a lattice of spacing ``length_mm / 3`` that covers
    ``grid`` and read at its voxel centres by cubic B-splines (the field of the whole
    resolution at a fraction of the cost), then scaled so that the largest displacement at
    the mesh's nodes is ``shift_mm``.  Unlike :func:`bump_field` the brain is deformed
    everywhere, in directions that vary over tens of millimetres.

    Such a field changes volume by tens of percent where it varies (its divergence is of the
    order of ``shift_mm / length_mm``), which brain tissue, nearly incompressible, does not:
    an FE model fits it with compressible tissue, low ``lam / mu``.  With ``solenoidal`` the
    field is the curl of such a random vector potential instead, divergence-free (volume
    preserving to second order) up to the lattice's central differences: shift without
    compression, as an incompressible tissue would move.

    Parameters
    ----------
    grid : Image
        The grid (``f``'s), world mm.
    mesh : Mesh
        Its nodes set the scale.
    shift_mm : float
        Largest displacement at the nodes, mm (realistic brain shift: 5-15 mm).
    length_mm : float
        sd of the smoothing Gaussian, mm.
    seed : int
        Seed of NumPy's generator (the same seed, grid and mesh give the same field).
    solenoidal : bool
        The curl of a random vector potential (divergence-free) instead of the field itself.

    Returns
    -------
    Image
        ``(I, J, K, 3)`` float64 displacement in world mm, ``grid``'s affine.

    Raises
    ------
    ValueError
        Non-positive ``shift_mm`` or ``length_mm``, or a field whose map ``x -> x + u(x)``
        folds or nearly folds the image (the determinant of its Jacobian below 0.2 at a
        voxel: lower ``shift_mm`` or raise ``length_mm``).
    """
    import scipy.ndimage as ndi

    if shift_mm <= 0 or length_mm <= 0:
        raise ValueError("shift_mm and length_mm must be > 0")
    pts = grid_points(grid)
    h = length_mm / 3.0
    lo = pts.min(axis=0) - 4.0 * length_mm
    n = np.ceil((pts.max(axis=0) + 4.0 * length_mm - lo) / h).astype(int) + 1
    rng = np.random.default_rng(seed)
    coarse = [ndi.gaussian_filter(rng.standard_normal(tuple(n)), 3.0, mode="wrap") for _ in range(3)]
    if solenoidal:  # u = curl A on the lattice (its axes are the world's; the scale is set below)
        d = [np.gradient(a) for a in coarse]  # d[c][axis] = d A_c / d x_axis
        coarse = [d[2][1] - d[1][2], d[0][2] - d[2][0], d[1][0] - d[0][1]]

    def at(points):
        c = ((points - lo) / h).T
        return np.stack([ndi.map_coordinates(v, c, order=3, mode="nearest") for v in coarse], -1)

    scale = shift_mm / np.linalg.norm(at(mesh.nodes), axis=1).max()
    u = scale * at(pts).reshape(*grid.data.shape[:3], 3)
    # the Jacobian of x + u(x) in world coordinates: I + (d u / d index) A^-1, slab by slab
    # along the first axis (a 1 mm head grid would need gigabytes at once)
    a_inv = np.linalg.inv(grid.affine[:3, :3])
    det_min = np.inf
    for i0 in range(0, u.shape[0], 32):
        lo_i, hi_i = max(i0 - 1, 0), min(i0 + 33, u.shape[0])
        if hi_i - lo_i < 2:
            continue
        du = np.stack(np.gradient(u[lo_i:hi_i], axis=(0, 1, 2)), axis=-1)
        det_min = min(det_min, float(np.linalg.det(np.eye(3) + du @ a_inv).min()))
    if det_min < 0.2:
        raise ValueError(f"a random field of {shift_mm:g} mm at the nodes with length "
                         f"{length_mm:g} mm (nearly) folds the image: Jacobian determinant "
                         f"{det_min:.2f} at a voxel (lower shift_mm or raise length_mm)")
    return Image(u, grid.affine)


def field_truth(mesh: Mesh, field: Image, *, n_pushed=20) -> Truth:
    """A truth the model did not make: a dense displacement field sampled at the nodes.

    Parameters
    ----------
    mesh : Mesh
    field : Image
        ``(I, J, K, 3)`` displacement, world mm (e.g. :func:`bump_field`, or another
        registration's field read by :func:`bayesreg.interop.transforms.load_displacement` and put
        on ``f``'s grid).
    n_pushed : int
        The ``n_pushed`` nodes of largest displacement are recorded as ``pushed``.

    Returns
    -------
    Truth
        ``u`` the trilinear interpolation of ``field`` at the nodes, ``lam_e = mu_e =
        None``, ``field`` kept.
    """
    from bayesreg.data.registration import displacement_at

    u = displacement_at(field, mesh.nodes)
    pushed = np.argsort(-np.linalg.norm(u, axis=1))[:max(1, min(int(n_pushed), len(u)))]
    return Truth(u, None, None, np.sort(pushed), field)


def fe_field(mesh: Mesh, u, grid: Image, *, extend_k: int = 8) -> Image:
    """The FE displacement of nodal values ``u`` on the voxel centres of ``grid``.

    Inside the undeformed mesh the linear interpolation of ``u`` in each tetrahedron
    (:func:`bayesreg.mesh.warp.interpolation_matrix`); beyond it, the inverse-square-distance
    mean of the displacements of the ``extend_k`` nearest boundary nodes
    (:func:`bayesreg.mesh.warp.continue_displacement`, the continuation
    :func:`bayesreg.mesh.warp.warp_image` uses with ``outside="extend"``).

    Parameters
    ----------
    mesh : Mesh
    u : (N, 3) array
        Nodal displacements, mm.
    grid : Image
        The grid (``f``'s), world mm.
    extend_k : int
        Boundary nodes averaged beyond the mesh.

    Returns
    -------
    Image
        ``(I, J, K, 3)`` float64 displacement, world mm, ``grid``'s affine.
    """
    from bayesreg.mesh.warp import continue_displacement, interpolation_matrix

    u = np.asarray(u, np.float64)
    w, inside = interpolation_matrix(mesh, grid)
    inside = np.ravel(inside)
    out = np.asarray(w @ u)
    if not np.all(inside):
        b = np.asarray(mesh.boundary)
        out[~inside] = continue_displacement(grid_points(grid)[~inside], mesh.nodes[b], u[b],
                                             k=extend_k)
    return Image(out.reshape(*grid.data.shape[:3], 3), grid.affine)


def with_discrepancy(truth: Truth, mesh: Mesh, extra: Image) -> Truth:
    """An FE truth plus a dense field the FE model does not make (a known model discrepancy).

    The dense truth is :func:`fe_field` of ``truth.u`` plus ``extra`` on ``extra``'s grid;
    at the nodes, ``truth.u`` plus ``extra`` read trilinearly there.  The Lamé parameters
    and the pushed nodes are kept, so the ratios keep their truths while
    :attr:`Truth.made_by_model` is false: the FE model with those parameters explains the
    shift only up to ``extra``'s part that no FE field follows (what a model discrepancy,
    ``model.discrepancy``, is for).

    Parameters
    ----------
    truth : Truth
        An FE truth (``lam_e`` known, no dense field).
    mesh : Mesh
    extra : Image
        ``(I, J, K, 3)`` displacement, world mm, on ``f``'s grid (e.g. :func:`random_field`).

    Returns
    -------
    Truth

    Raises
    ------
    ValueError
        ``truth`` is not an FE truth, or ``extra`` is not a displacement field.
    """
    from bayesreg.data.registration import displacement_at

    if not truth.made_by_model:
        raise ValueError("with_discrepancy adds to an FE truth (known lam, mu and no dense field)")
    data = np.asarray(extra.data, np.float64)
    if data.ndim != 4 or data.shape[-1] != 3:
        raise ValueError(f"the added field must be (I, J, K, 3), got {data.shape}")
    field = Image(fe_field(mesh, truth.u, extra).data + data, extra.affine)
    u = truth.u + displacement_at(extra, mesh.nodes)
    return Truth(u, truth.lam_e, truth.mu_e, truth.pushed, field)


# ----------------------------------------------------------------------------------------
# Ground truth of paper Sec. 4.1: energy minimiser under the skull constraint
# ----------------------------------------------------------------------------------------



"""The posterior of paper Eqs. 8-12 over boundary displacements and Lamé parameters.

``log p(u_b, lam, mu | m) = -E_s(u) / T_s - E_r(u; lam, mu) / T_r + log p(lam) + log p(mu)``
(+ const), where ``u`` on the interior nodes solves ``K_ii u_i = -K_ib u_b`` (Sec. 3.3:
only boundary nodes are sampled), ``E_s`` is the SSD of Eq. 1 (:mod:`bayesreg.similarity`)
and ``E_r`` the strain energy of Eqs. 2-3.  The Lamé parameters live on groups of
elements: one group (uniform), one per tissue (CSF, GM, WM) or one per element; one of
them can be held fixed to pin the scale (Sec. 3.3).  Priors are Beta(A, B) scaled to
``[r1, r2]`` (Sec. 3.1, via NumPyro).

Hard constraints (Sec. 3.2) give ``log p = -inf``: a node inside the forbidden (skull)
region or outside the image, a parameter outside its prior support or non-positive, an
inverted element in the deformed mesh.  A CG solve that does not converge also gives
``-inf`` (the proposal is rejected) and is flagged in :class:`Aux` so that the driver
counts and reports it: it is never silently accepted.  An optional smooth barrier of width
``w`` (:func:`skull_barrier`, ``barrier_mm`` of :func:`build_posterior`) bends the
log-density down near the skull for gradient kernels; the hard constraint stays.

Position layout: one flat float64 vector ``theta = [u_b.ravel(), phi]`` with ``u_b``
node-major (``3*i + axis``, mm) and ``phi`` the free elastic parameters.  Gradient kernels
move ``eta`` instead of ``phi``, the logit of ``phi`` on its prior support ``(r1, r2)``
(:func:`from_unconstrained`, with the log-Jacobian).

The exact normaliser (``prior_normaliser: exact``, :func:`log_normaliser`): with the interior
nodes at the FE solution, ``E_r = u_b^T S u_b / 2`` with ``S = K_bb - K_bi K_ii^-1 K_ib`` the
Schur complement of ``K`` on the boundary DOFs, so the prior ``exp(-E_r / T_r)`` of Eq. 12 is
a Gaussian on ``u_b`` (on the complement of the six rigid-body modes, the null space of
``S``) whose normaliser is ``(1/2) log pdet S(lam, mu) + const``.  The paper drops it (its
Sec. 3.3), which biases the elastic parameters toward zero.
"""

from __future__ import annotations

from collections.abc import Mapping
from functools import partial
from typing import NamedTuple

import numpy as np

from bayesreg import _xla

_xla.configure()
import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpyro.distributions as dist  # noqa: E402

from bayesreg.fem import (  # noqa: E402
    ElasticOperator,
    GroupBlocks,
    build_operator,
    element_strain_energy,
    group_blocks,
    shape_gradients,
)
from bayesreg.images import _check_image  # noqa: E402
from bayesreg.mesh import Mesh  # noqa: E402
from bayesreg.similarity import SSDTerm, ssd_residuals  # noqa: E402
from bayesreg.solver import (  # noqa: E402
    DENSE_MAX_DOFS,
    DensePreconditioner,
    SolveInfo,
    SpectralPreconditioner,
    _check_shape,
    dense_preconditioner,
    interior_map_blocks,
    solve_interior_blocks,
    spectral_preconditioner,
)

__all__ = [
    "Posterior",
    "Aux",
    "ParamLayout",
    "build_posterior",
    "with_skull_barrier",
    "skull_barrier",
    "skull_distance",
    "log_density",
    "log_density_condensed",
    "condensation",
    "preconditioner",
    "split_position",
    "elastic_groups",
    "full_displacement",
    "energies",
    "stiffness_blocks",
    "MAX_GROUPED",
    "SCOPES",
    "from_unconstrained",
    "to_unconstrained",
    "log_normaliser",
    "add_normaliser",
]


#: At most this many parameter groups get shared per-group stiffness blocks
#: (:class:`bayesreg.fem.GroupBlocks`, ``144 G n_i (S_i + S_b)`` bytes); more (the
#: per-element model) assemble ``K`` from the elements at each evaluation.
MAX_GROUPED = 16

#: Names (:func:`jax.named_scope`) of the parts of :func:`log_density`, carried into the
#: compiled program's metadata (no cost at run time): a profile of the compiled step can
#: then attribute its time to them (``benchmarks/profiling.py``: ``run.py``'s figure 2b,
#: ``profile_step.py``).
SCOPES = {
    "stiffness": "bayesreg_stiffness",  # K_ii, K_ib blocks at the position's lam, mu
    "solve": "bayesreg_solve",  # the interior CG solve
    "similarity": "bayesreg_similarity",  # E_s at the Gauss points (Eq. 1)
    "strain_energy": "bayesreg_strain_energy",  # E_r (Eqs. 2-7)
    "constraints": "bayesreg_constraints",  # prior support, inverted elements, skull, barrier
}


class ParamLayout(NamedTuple):
    """Host-side description of the elastic parameters (names for reports).

    Attributes
    ----------
    group_names : tuple of str
        ``("all",)``, ``("csf", "gm", "wm")`` or ``("e0", ...)``.
    free : tuple of (str, int)
        ``("lam" | "mu", group)`` of each free parameter, in ``phi`` order.
    fixed : tuple of (str, int, float)
        Parameters held fixed.
    """

    group_names: tuple
    free: tuple
    fixed: tuple

    @property
    def free_names(self) -> list[str]:
        return [f"{p}_{self.group_names[g]}" for p, g in self.free]


class Posterior(NamedTuple):
    """Static data of the log-density (a pytree of arrays; see module docstring).

    Attributes
    ----------
    op : ElasticOperator
    nodes : (N, 3)  world mm
    tets : (M, 4) int
    grads : (M, 4, 3)  shape-function gradients, 1/mm
    volumes : (M,)  mm^3
    perm : (N,) int
        ``u = concat(u_b, u_i)[perm]`` scatters boundary/interior blocks to node order.
    boundary : (n_b,) int
    group : (M,) int
        Parameter group of each element.
    base : (2G,)
        ``[lam_0..lam_G-1, mu_0..mu_G-1]`` with the fixed values in place.
    free_index : (n_free,) int
        Position in ``base`` of each free parameter.
    prior_a, prior_b, prior_r1, prior_r2 : (n_free,)
        Scaled Beta prior of each free parameter.
    phi_ref : (n_free,)
        A valid parameter vector, substituted in the solve when a proposal leaves the
        support (its log-density is ``-inf`` anyway; this keeps ``K_ii`` SPD under vmap).
    ssd : SSDTerm
    forbidden : (I, J, K) bool
        Hard-constraint region (skull) on the label grid.
    forbidden_inv_affine : (4, 4)
    inv_t_s, inv_t_r : ()
        ``1 / T_s`` and ``1 / T_r``.
    dense_index : (M * 144,) int
        Flat position in the dense ``(3N, 3N)`` stiffness, DOFs ordered interior nodes first
        (in ``op``'s row order) then boundary nodes, of each entry of the element matrices
        ``op.klam`` / ``op.kmu`` (for :func:`log_normaliser`).
    rigid_b : (3 n_b, 6)
        Orthonormal basis of the rigid-body modes restricted to the boundary DOFs (the null
        space of the Schur complement ``S``).
    voxel_size : (3,)
        Spacing of the forbidden region's grid, mm (the column norms of its affine).
    barrier_offsets : (K, 3) int
        Voxel offsets around a point's nearest voxel whose cubes the skull barrier looks
        at (``{-R..R}^3``, ``R = max(1, ceil(w / min voxel_size))``: every cube nearer than
        ``w``; ``(0, 3)`` when off).
    barrier_width : ()
        Width ``w`` (mm) of the skull barrier, 0 = off (:func:`skull_barrier`).
    unit_blocks : GroupBlocks or None
        Per-group unit blocks of ``K_ii``, ``K_ib`` when there are at most
        ``MAX_GROUPED`` groups (uniform and tissue models), else ``None`` (per-element
        model: the blocks are assembled from the elements); see :func:`stiffness_blocks`.
    spectral : SpectralPreconditioner or None
        The exact CG preconditioner of a one-group model at every ``lam, mu``
        (``build_posterior(spectral=True)``), shared by all chains; :func:`log_density`
        uses it when no other preconditioner is given.
    """

    op: ElasticOperator
    nodes: jax.Array
    tets: jax.Array
    grads: jax.Array
    volumes: jax.Array
    perm: jax.Array
    boundary: jax.Array
    group: jax.Array
    base: jax.Array
    free_index: jax.Array
    prior_a: jax.Array
    prior_b: jax.Array
    prior_r1: jax.Array
    prior_r2: jax.Array
    phi_ref: jax.Array
    ssd: SSDTerm
    forbidden: jax.Array
    forbidden_inv_affine: jax.Array
    inv_t_s: jax.Array
    inv_t_r: jax.Array
    dense_index: jax.Array
    rigid_b: jax.Array
    voxel_size: jax.Array
    barrier_offsets: jax.Array
    barrier_width: jax.Array
    unit_blocks: GroupBlocks | None = None
    spectral: SpectralPreconditioner | None = None

    @property
    def n_boundary(self) -> int:
        return self.boundary.shape[0]

    @property
    def n_free(self) -> int:
        return self.free_index.shape[0]

    @property
    def dim(self) -> int:
        return 3 * self.n_boundary + self.n_free


class Aux(NamedTuple):
    """By-products of one log-density evaluation.

    Attributes
    ----------
    interior : (n_i, 3)  interior displacements (the next warm start), mm
    solve : SolveInfo
    e_s, e_r : ()  similarity and strain energies
    """

    interior: jax.Array
    solve: SolveInfo
    e_s: jax.Array
    e_r: jax.Array


def build_posterior(
    mesh: Mesh,
    ssd_term: SSDTerm,
    forbidden,
    *,
    t_s: float,
    t_r: float,
    layout: ParamLayout,
    element_group,
    prior: dict,
    phi_ref,
    barrier_mm: float = 0.0,
    spectral: bool = False,
) -> Posterior:
    """Assemble :class:`Posterior` from a mesh, the SSD term and the parameter layout.

    Parameters
    ----------
    mesh : Mesh
    ssd_term : SSDTerm
    forbidden : Image
        Boolean/0-1 image of the hard-constraint (skull) region.
    t_s, t_r : float
        Temperatures of Eqs. 11-12 (> 0).
    layout : ParamLayout
    element_group : (M,) int
        Parameter group of each element.
    prior : dict
        ``{"lam": (A, B, r1, r2), "mu": ...}`` (one prior for every group) or
        ``{"lam": [(A, B, r1, r2) per group], ...}``.
    phi_ref : (n_free,) array_like
        A valid parameter vector (inside the prior support).
    barrier_mm : float
        Width (mm) of the optional smooth skull barrier (:func:`skull_barrier`); 0 = off.
    spectral : bool
        Build :attr:`Posterior.spectral` (one parameter group and ``3 n_i <=
        DENSE_MAX_DOFS`` only; ignored otherwise).

    Raises
    ------
    ValueError
        Non-positive temperatures; a ``prior`` that is not a dict with an entry for each
        kind of free parameter (``"lam"``, ``"mu"``), each one ``(A, B, r1, r2)`` or one
        such tuple per group, with finite ``A, B > 0`` and ``0 <= r1 < r2 < inf``;
        ``phi_ref`` not of shape ``(n_free,)`` or not strictly inside its support (NaN
        included); ``forbidden`` not a 3D :class:`~bayesreg.images.Image` with a finite
        invertible affine; or a negative barrier width.
    """
    if not (t_s > 0 and t_r > 0 and np.isfinite(t_s) and np.isfinite(t_r)):
        raise ValueError(f"temperatures must be finite and > 0, got T_s={t_s}, T_r={t_r}")
    forbidden = _check_image(forbidden, "forbidden")
    n_groups = len(layout.group_names)
    base = np.ones(2 * n_groups)
    for p, g, v in layout.fixed:
        if v <= 0:
            raise ValueError(f"fixed {p}_{layout.group_names[g]} must be > 0, got {v}")
        base[g + (n_groups if p == "mu" else 0)] = v
    free_index = np.array([g + (n_groups if p == "mu" else 0) for p, g in layout.free], int)
    pri = _prior_table(prior, layout)
    a, b, r1, r2 = pri.T
    phi_ref = np.asarray(phi_ref, dtype=np.float64)
    if phi_ref.shape != (len(layout.free),):
        raise ValueError(f"phi_ref must have shape ({len(layout.free)},) (one value per free "
                         f"parameter), got {phi_ref.shape}")
    outside = ~((phi_ref > r1) & (phi_ref < r2))
    if np.any(outside):
        bad = [f"{layout.free_names[k]}={phi_ref[k]:g} not in ({r1[k]:g}, {r2[k]:g})"
               for k in np.flatnonzero(outside)[:5]]
        more = f" and {int(outside.sum()) - 5} more" if outside.sum() > 5 else ""
        raise ValueError(f"reference parameters phi_ref lie outside the prior support: "
                         f"{', '.join(bad)}{more}")
    op, interior = build_operator(mesh.nodes, mesh.tets, mesh.boundary)
    n_b, n_i = len(mesh.boundary), len(interior)
    perm = np.empty(len(mesh.nodes), np.int64)
    perm[mesh.boundary] = np.arange(n_b)
    perm[interior] = n_b + np.arange(n_i)
    grads, vol = shape_gradients(mesh.nodes, mesh.tets)
    # dense layout for the exact normaliser: interior DOFs first, then boundary DOFs
    dense_pos = np.where(perm >= n_b, perm - n_b, perm + n_i)
    dof = (3 * dense_pos[np.asarray(mesh.tets)][:, :, None] + np.arange(3)).reshape(-1, 12)
    n_dof = 3 * len(mesh.nodes)
    dense_index = (dof[:, :, None] * n_dof + dof[:, None, :]).reshape(-1)
    xb = np.asarray(mesh.nodes, np.float64)[np.asarray(mesh.boundary)]
    xb = xb - xb.mean(axis=0)
    rigid = np.zeros((n_b, 3, 6))
    for k in range(3):
        rigid[:, k, k] = 1.0
        rigid[:, :, 3 + k] = np.cross(np.eye(3)[k], xb)
    rigid_b = np.linalg.qr(rigid.reshape(-1, 6))[0]
    spacing = np.linalg.norm(np.asarray(forbidden.affine, dtype=np.float64)[:3, :3], axis=0)
    post = Posterior(
        op=op,
        nodes=jnp.asarray(mesh.nodes),
        tets=jnp.asarray(mesh.tets, dtype=jnp.int32),
        grads=jnp.asarray(grads),
        volumes=jnp.asarray(np.abs(vol)),
        perm=jnp.asarray(perm, dtype=jnp.int32),
        boundary=jnp.asarray(mesh.boundary, dtype=jnp.int32),
        group=jnp.asarray(element_group, dtype=jnp.int32),
        base=jnp.asarray(base),
        free_index=jnp.asarray(free_index, dtype=jnp.int32),
        prior_a=jnp.asarray(a),
        prior_b=jnp.asarray(b),
        prior_r1=jnp.asarray(r1),
        prior_r2=jnp.asarray(r2),
        phi_ref=jnp.asarray(phi_ref),
        ssd=ssd_term,
        forbidden=jnp.asarray(np.asarray(forbidden.data) > 0),
        forbidden_inv_affine=jnp.asarray(np.linalg.inv(forbidden.affine)),
        inv_t_s=jnp.asarray(1.0 / t_s),
        inv_t_r=jnp.asarray(1.0 / t_r),
        dense_index=jnp.asarray(dense_index, dtype=jnp.int32 if n_dof**2 < 2**31 else jnp.int64),
        rigid_b=jnp.asarray(rigid_b),
        voxel_size=jnp.asarray(spacing),
        barrier_offsets=jnp.zeros((0, 3), dtype=jnp.int32),
        barrier_width=jnp.asarray(0.0),
        unit_blocks=group_blocks(op, element_group, n_groups) if n_groups <= MAX_GROUPED else None,
    )
    if spectral and n_groups == 1 and 3 * n_i <= DENSE_MAX_DOFS:
        ub = post.unit_blocks
        post = post._replace(spectral=spectral_preconditioner(op, *ub.group(0)))
    return with_skull_barrier(post, barrier_mm)


def _prior_table(prior, layout: ParamLayout) -> np.ndarray:
    """``(n_free, 4)`` rows ``(A, B, r1, r2)`` of the free parameters (:func:`build_posterior`);
    ``ValueError`` naming the entry that is missing, of the wrong shape or invalid."""
    n_groups = len(layout.group_names)
    if not isinstance(prior, Mapping):
        raise ValueError(f"prior must be a dict {{'lam': (A, B, r1, r2), 'mu': ...}}, got "
                         f"{type(prior).__name__}")
    entries = {}
    for p in sorted({p for p, _ in layout.free}):
        if p not in prior:
            needed = next(n for n, (q, _) in zip(layout.free_names, layout.free) if q == p)
            raise ValueError(f"prior has no {p!r} entry (needed by the free parameter {needed}); "
                             f"expected {{'lam': (A, B, r1, r2), 'mu': (A, B, r1, r2)}}")
        try:
            pr = np.asarray(prior[p], dtype=np.float64)
        except (TypeError, ValueError):
            pr = None
        if pr is None or pr.shape not in ((4,), (n_groups, 4)):
            got = "a ragged or non-numeric sequence" if pr is None else f"shape {pr.shape}"
            raise ValueError(f"prior[{p!r}] must be (A, B, r1, r2) or one such tuple per group, "
                             f"shape ({n_groups}, 4); got {got}")
        entries[p] = pr
    rows = np.array([entries[p] if entries[p].ndim == 1 else entries[p][g] for p, g in layout.free],
                    dtype=np.float64).reshape(-1, 4)
    a, b, r1, r2 = rows.T
    ok = np.all(np.isfinite(rows), axis=1) & (a > 0) & (b > 0) & (r1 >= 0) & (r1 < r2)
    if not np.all(ok):
        k = int(np.argmin(ok))
        raise ValueError(f"invalid Beta prior of {layout.free_names[k]}: need finite A, B > 0 and "
                         f"0 <= r1 < r2 < inf, got (A, B, r1, r2) = "
                         f"({', '.join(f'{v:g}' for v in rows[k])})")
    return rows


def with_skull_barrier(post: Posterior, barrier_mm: float) -> Posterior:
    """``post`` with the skull barrier of width ``barrier_mm`` (mm; 0 = off) in place of its
    own (:func:`skull_barrier`): sets :attr:`Posterior.barrier_width` and the voxel offsets
    searched, ``{-R..R}^3`` with ``R = max(1, ceil(w / min voxel_size))`` (a cube at offset
    ``k`` is at least ``(k - 1) h`` away, so every cube nearer than ``w`` is searched).

    Raises
    ------
    ValueError
        ``barrier_mm`` negative or not finite.
    """
    if not (barrier_mm >= 0 and np.isfinite(barrier_mm)):
        raise ValueError(f"the skull barrier width must be finite and >= 0 mm, got {barrier_mm}")
    offsets = np.zeros((0, 3), dtype=np.int32)
    if barrier_mm > 0:
        r = max(1, int(np.ceil(barrier_mm / float(np.min(np.asarray(post.voxel_size))) - 1e-12)))
        rng = np.arange(-r, r + 1)
        offsets = np.stack(np.meshgrid(rng, rng, rng, indexing="ij"), -1).reshape(-1, 3)
    return post._replace(barrier_offsets=jnp.asarray(offsets, dtype=jnp.int32),
                         barrier_width=jnp.asarray(float(barrier_mm)))


def skull_distance(post: Posterior, points):
    """Smoothed distance (mm) from each point to the forbidden region as the hard
    constraint sees it: the union of the cubes (voxel cells) of the forbidden voxels.

    ``d = -tau log sum_k exp(-d_k / tau)`` over the forbidden cubes ``k`` among the
    :attr:`Posterior.barrier_offsets` around the point's nearest voxel (voxels outside the
    grid count as forbidden, as in the hard rule), ``d_k`` the Euclidean distance to cube
    ``k`` in mm, ``tau = w / 20``.  The soft minimum is C-infinity where the cubes' distances
    are (outside every cube) and never exceeds the true distance, so ``d <= 0`` whenever the
    nearest-voxel rule says "forbidden"; the cubes searched cover every cube nearer than
    ``w``.  Exact for an affine with orthogonal columns (cubes are boxes of
    :attr:`Posterior.voxel_size`); approximate for an oblique one.

    Parameters
    ----------
    post : Posterior  with ``barrier_width > 0``
    points : (P, 3) array  world mm

    Returns
    -------
    (P,) array  mm (``+inf`` where no forbidden cube is searched)
    """
    c = _voxel_coordinates(post, points)
    v = jnp.floor(c + 0.5)  # nearest voxel (the hard rule's)
    cells = v[:, None, :] + post.barrier_offsets  # (P, K, 3)
    gap = jnp.maximum(jnp.abs(c[:, None, :] - cells) - 0.5, 0.0) * post.voxel_size
    s2 = jnp.sum(gap * gap, axis=-1)
    dist = jnp.where(s2 > 0, jnp.sqrt(jnp.where(s2 > 0, s2, 1.0)), 0.0)  # 0 inside the cube
    forb = _voxel_forbidden(post, cells.astype(jnp.int32))
    tau = post.barrier_width / 20.0
    z = jnp.where(forb, -dist / tau, -jnp.inf)
    return -tau * jax.nn.logsumexp(z, axis=-1)


def skull_barrier(post: Posterior, points):
    """Smooth barrier against the skull: ``-sum (w / d - 1)^2`` over the points with
    ``0 < d < w`` (``d`` = :func:`skull_distance`, ``w = barrier_width``), 0 beyond ``w``,
    ``-> -inf`` as ``d -> 0``; C1 in the points.

    An optional change of the model (``model.skull_barrier_mm``: 1 mm for new configs; 0 =
    off, the paper's hard constraint alone, in the paper's configs;
    measured in ``benchmarks/barrier.py``): it bends the log-density down within ``w`` of the
    skull so that gradient trajectories turn before they reach the hard ``-inf`` wall, which
    stays in place (no stored draw can violate it).  ``d`` is the distance to the voxel
    cubes that the hard rule forbids, so the barrier's singularity is never behind the
    wall: a first version interpolated a signed distance trilinearly, which at the corners
    of the voxel staircase still read up to 0.5-1 mm of clearance in 19% of the forbidden
    points near the paper's truth (where a trajectory then met the wall unannounced).

    Parameters
    ----------
    post : Posterior
    points : (P, 3) array  deformed node positions, world mm

    Returns
    -------
    () array
    """
    w = post.barrier_width
    if post.barrier_offsets.shape[0] == 0:
        return jnp.zeros(())
    d = skull_distance(post, points)
    near = d < w
    d_safe = jnp.where(near, jnp.maximum(d, 1e-6 * jnp.maximum(w, 1e-12)), 1.0)
    return -jnp.sum(jnp.where(near, (w / d_safe - 1.0) ** 2, 0.0))


def _check_last_axis(name, value, n, what):
    """``value`` is ``(..., n)`` (batched arrays allowed)."""
    shape = jnp.shape(value)
    if len(shape) < 1 or shape[-1] != n:
        raise ValueError(f"{name} must have shape (..., {n}) ({what}), got {shape}")


def _check_theta(post: Posterior, theta):
    _check_shape("theta", theta, (post.dim,),
                 f"[u_b.ravel(), phi]: 3 * {post.n_boundary} boundary DOFs + {post.n_free} free "
                 "parameters")


def split_position(post: Posterior, theta):
    """``theta`` ``(dim,)`` -> ``u_b`` ``(n_b, 3)`` mm and ``phi`` ``(n_free,)``.

    Raises
    ------
    ValueError
        ``theta`` not of shape ``(dim,)`` (one position; map batches with ``vmap``).
    """
    _check_theta(post, theta)
    nb3 = 3 * post.n_boundary
    return theta[:nb3].reshape(-1, 3), theta[nb3:]


@jax.jit
def elastic_groups(post: Posterior, phi):
    """Lamé parameters per group from the free parameters (jitted: called on the host on
    batches of draws, and inlined where it is traced).

    Parameters
    ----------
    post : Posterior
    phi : (..., n_free) array  (batched draws allowed)

    Returns
    -------
    lam_g, mu_g : (..., G) arrays, the fixed parameters in place

    Raises
    ------
    ValueError
        ``phi`` not of shape ``(..., n_free)``.
    """
    phi = jnp.asarray(phi)
    _check_last_axis("phi", phi, post.n_free, "the free elastic parameters")
    full = jnp.broadcast_to(post.base, phi.shape[:-1] + post.base.shape)
    full = full.at[..., post.free_index].set(phi)
    g = post.base.shape[0] // 2
    return full[..., :g], full[..., g:]


def full_displacement(post: Posterior, u_b, u_i):
    """Nodal displacements ``(N, 3)`` from boundary and interior blocks (node order).

    Raises
    ------
    ValueError
        ``u_b`` not ``(n_b, 3)`` or ``u_i`` not ``(n_i, 3)``.
    """
    _check_shape("u_b", u_b, (post.n_boundary, 3), "one row per boundary node")
    _check_shape("u_i", u_i, (post.op.n_interior, 3), "one row per interior node")
    return jnp.concatenate([u_b, u_i], axis=0)[post.perm]


def _log_prior(post: Posterior, phi):
    x = (phi - post.prior_r1) / (post.prior_r2 - post.prior_r1)
    inside = (x > 0) & (x < 1) & (phi > 0)
    xs = jnp.clip(x, 1e-12, 1 - 1e-12)
    lp = dist.Beta(post.prior_a, post.prior_b).log_prob(xs) - jnp.log(post.prior_r2 - post.prior_r1)
    return jnp.sum(lp), jnp.all(inside)


def _voxel_coordinates(post: Posterior, points):
    """Continuous voxel coordinates ``(..., 3)`` of world points on the forbidden grid."""
    return points @ post.forbidden_inv_affine[:3, :3].T + post.forbidden_inv_affine[:3, 3]


def _voxel_forbidden(post: Posterior, idx):
    """Whether the voxels ``idx`` ``(..., 3)`` int are forbidden (outside the grid counts)."""
    shape = jnp.array(post.forbidden.shape)
    inside = jnp.all((idx >= 0) & (idx < shape), axis=-1)
    idc = jnp.clip(idx, 0, shape - 1)
    return ~inside | post.forbidden[idc[..., 0], idc[..., 1], idc[..., 2]]


def _node_forbidden(post: Posterior, points):
    idx = jnp.floor(_voxel_coordinates(post, points) + 0.5).astype(jnp.int32)  # nearest voxel
    return _voxel_forbidden(post, idx)  # (as scipy's order-0)


def stiffness_blocks(post: Posterior, lam_g, mu_g):
    """ELL blocks ``(b_ii, b_ib)`` of ``K_ii``, ``K_ib`` (paper Eqs. 5-7) for per-group
    Lamé parameters ``lam_g``, ``mu_g`` ``(G,)``.

    From the shared per-group unit blocks (:class:`bayesreg.fem.GroupBlocks`) when the
    posterior has them, else assembled from the elements
    (:meth:`bayesreg.fem.ElasticOperator.blocks`); the two agree to round-off (tested).
    """
    if post.unit_blocks is not None:
        return post.unit_blocks.combine(lam_g, mu_g)
    return post.op.blocks(lam_g[post.group], mu_g[post.group])


def energies(post: Posterior, u, phi):
    """``(E_s, E_r)`` for nodal displacements ``u`` ``(N, 3)`` and parameters ``phi``
    ``(n_free,)``.

    Raises
    ------
    ValueError
        ``u`` not ``(N, 3)`` or ``phi`` not ``(n_free,)``.
    """
    _check_shape("u", u, tuple(post.nodes.shape), "one row per node")
    _check_shape("phi", phi, (post.n_free,), "the free elastic parameters")
    lam_g, mu_g = elastic_groups(post, phi)
    u_e = u[post.tets]
    with jax.named_scope(SCOPES["strain_energy"]):
        e_r = element_strain_energy(post.grads, post.volumes, u_e, lam_g[post.group], mu_g[post.group])
    with jax.named_scope(SCOPES["similarity"]):
        r = ssd_residuals(post.ssd, u_e)
        e_s = jnp.sum(r * r)
    return e_s, e_r


def log_density(post: Posterior, theta, u_i0, *, rtol=1e-8, maxiter=1000,
                precond: DensePreconditioner | None = None):
    """Unnormalised log posterior (paper Eqs. 9, 11, 12) and its by-products.

    A position that breaks a constraint known before the solve, a parameter outside the
    prior support or a boundary node in the forbidden region, gives ``-inf`` at once: a
    :func:`jax.lax.cond` skips the solve and the energies where one branch runs (a chain
    mapped or alone on a CPU).  Under ``vmap`` both branches run, and the solve is made at
    :attr:`Posterior.phi_ref` (``K_ii`` stays positive definite) with an iteration cap of 0,
    so that no batched CG waits for it.  A skipped solve reports 0 iterations and is not a
    failure.  (The paper's joint random walk proposes such positions often: once its drift
    has brought parameters near 0, 57-68% of its proposals leave the support on the
    paper-size mesh, and nodes sliding on the skull step into it.)

    Parameters
    ----------
    post : Posterior
    theta : (dim,) array
        ``[u_b.ravel() (mm), phi]``.
    u_i0 : (n_i, 3) array
        Warm start of the interior solve (mm).
    rtol, maxiter
        CG tolerance (relative residual) and iteration cap.
    precond : DensePreconditioner, optional
        CG preconditioner (:func:`preconditioner`, at any parameters); default
        :attr:`Posterior.spectral` at the position's parameters where the posterior has
        one, else block Jacobi.  It changes the CG's iterations, not the tolerance it meets.

    Returns
    -------
    logp : ()
        ``-inf`` on a hard-constraint violation or a non-converged solve.
    aux : Aux
        ``e_s`` and ``e_r`` are 0 where the energies were skipped.

    Raises
    ------
    ValueError
        ``theta`` not of shape ``(dim,)`` or ``u_i0`` not ``(n_i, 3)`` (static shape checks:
        under ``vmap`` over chains these are the shapes of one chain).  Values are never
        checked: an invalid position gives ``-inf``.
    """
    u_b, phi = split_position(post, theta)
    _check_shape("u_i0", u_i0, (post.op.n_interior, 3), "warm start, one row per interior node")
    with jax.named_scope(SCOPES["constraints"]):
        log_prior, in_support = _log_prior(post, phi)
        phi_solve = jnp.where(in_support, phi, post.phi_ref)
        allowed = in_support & ~jnp.any(_node_forbidden(post, post.nodes[post.boundary] + u_b))

    def evaluate(_):
        lam_g, mu_g = elastic_groups(post, phi_solve)
        with jax.named_scope(SCOPES["stiffness"]):
            blocks = stiffness_blocks(post, lam_g, mu_g)
        with jax.named_scope(SCOPES["solve"]):
            u_i, info = solve_interior_blocks(
                post.op, *blocks, u_b, u_i0, rtol=rtol, maxiter=jnp.where(allowed, maxiter, 0),
                precond=_precond_at(post, precond, lam_g, mu_g))
        info = SolveInfo(info.iterations, info.residual, info.converged | ~allowed)
        return _finish(post, u_b, u_i, info, phi_solve, allowed, log_prior)

    def reject(_):
        zero = jnp.zeros((), u_b.dtype)
        info = SolveInfo(jnp.asarray(0), zero, jnp.asarray(True))
        aux = Aux(jax.lax.stop_gradient(jnp.asarray(u_i0, u_b.dtype)), info, zero, zero)
        return jnp.asarray(-jnp.inf, u_b.dtype), aux

    return jax.lax.cond(allowed, evaluate, reject, None)


def _precond_at(post: Posterior, precond, lam_g, mu_g):
    """The CG preconditioner of a solve at ``lam_g, mu_g``: ``precond`` if given, else the
    posterior's spectral one at those parameters, else ``None`` (block Jacobi)."""
    if precond is None and post.spectral is not None:
        return post.spectral._replace(lam=lam_g[0], mu=mu_g[0])
    return precond


def _finish(post: Posterior, u_b, u_i, info, phi_solve, in_support, log_prior):
    """Energies, hard constraints and ``log p`` from the boundary and interior displacements."""
    u = full_displacement(post, u_b, u_i)
    e_s, e_r = energies(post, u, phi_solve)
    with jax.named_scope(SCOPES["constraints"]):
        x = (post.nodes + u)[post.tets]
        det = jnp.einsum(
            "mi,mi->m", jnp.cross(x[:, 1] - x[:, 0], x[:, 2] - x[:, 0]), x[:, 3] - x[:, 0]
        )
        ok = (
            in_support
            & info.converged
            & jnp.all(det > 0)
            & ~jnp.any(_node_forbidden(post, post.nodes + u))
            & jnp.isfinite(e_s)
            & jnp.isfinite(e_r)
        )
        barrier = skull_barrier(post, post.nodes + u)
    logp = -e_s * post.inv_t_s - e_r * post.inv_t_r + log_prior + barrier
    return jnp.where(ok, logp, -jnp.inf), Aux(u_i, info, e_s, e_r)


def condensation(post: Posterior, theta):
    """Dense interior map ``H(phi)`` ``(3 n_i, 3 n_b)`` at the parameters of ``theta``
    (:func:`bayesreg.solver.interior_map_blocks` of :func:`stiffness_blocks`); the cache of
    :func:`log_density_condensed`."""
    _, phi = split_position(post, theta)
    _, in_support = _log_prior(post, phi)
    lam_g, mu_g = elastic_groups(post, jnp.where(in_support, phi, post.phi_ref))
    return interior_map_blocks(post.op, *stiffness_blocks(post, lam_g, mu_g), post.n_boundary)


def preconditioner(post: Posterior, theta) -> DensePreconditioner:
    """Dense CG preconditioner ``K_ii(phi)^-1`` (float32) at the parameters of ``theta``
    (:func:`bayesreg.solver.dense_preconditioner`; :attr:`Posterior.phi_ref` when they leave
    the prior support).  Built once per chain and reused while its parameters move: the
    preconditioner of :func:`log_density` (``precond``) at any nearby parameters."""
    _, phi = split_position(post, theta)
    _, in_support = _log_prior(post, phi)
    lam_g, mu_g = elastic_groups(post, jnp.where(in_support, phi, post.phi_ref))
    return dense_preconditioner(post.op, stiffness_blocks(post, lam_g, mu_g)[0])


def log_density_condensed(post: Posterior, theta, h):
    """:func:`log_density` with the interior from a cached condensation ``u_i = H u_b``.

    Exact (to the round-off of the Cholesky factorisation, far below the CG tolerance of
    :func:`log_density`) as long as ``h = condensation(post, theta')`` with ``theta'`` at
    the same elastic parameters as ``theta``: use it for moves of ``u_b`` alone.  A NaN map
    (factorisation failed) gives ``-inf``.

    Parameters
    ----------
    post : Posterior
    theta : (dim,) array  ``[u_b.ravel() (mm), phi]``
    h : (3 n_i, 3 n_b) array  interior map at ``theta``'s ``phi``

    Returns
    -------
    logp, aux : as :func:`log_density` (``aux.solve`` reports 0 iterations)

    Raises
    ------
    ValueError
        ``theta`` not of shape ``(dim,)`` or ``h`` not ``(3 n_i, 3 n_b)``.
    """
    u_b, phi = split_position(post, theta)
    _check_shape("h", h, (3 * post.op.n_interior, 3 * post.n_boundary),
                 "the interior map (3 n_i, 3 n_b) of condensation()")
    log_prior, in_support = _log_prior(post, phi)
    phi_solve = jnp.where(in_support, phi, post.phi_ref)
    u_i = (h @ u_b.reshape(-1)).reshape(-1, 3)
    finite = jnp.all(jnp.isfinite(u_i))
    info = SolveInfo(jnp.asarray(0), jnp.where(finite, 0.0, jnp.inf), finite)
    return _finish(post, u_b, u_i, info, phi_solve, in_support, log_prior)


def solve_position(post: Posterior, theta, u_i0=None, *, rtol=1e-8, maxiter=1000):
    """Full nodal displacement ``(N, 3)`` mm for a position ``(dim,)``, and the solve's
    :class:`~bayesreg.solver.SolveInfo` (host convenience: one jitted program per mesh
    size and tolerance, where running it op by op compiled about 60 small programs)."""
    if u_i0 is None:
        u_i0 = jnp.zeros((post.op.n_interior, 3))
    return _solve_position(post, jnp.asarray(theta), jnp.asarray(u_i0), rtol=float(rtol),
                           maxiter=int(maxiter))


@partial(jax.jit, static_argnames=("rtol", "maxiter"))
def _solve_position(post: Posterior, theta, u_i0, *, rtol, maxiter):
    u_b, phi = split_position(post, theta)
    lam_g, mu_g = elastic_groups(post, phi)
    u_i, info = solve_interior_blocks(
        post.op, *stiffness_blocks(post, lam_g, mu_g), u_b, u_i0, rtol=rtol, maxiter=maxiter,
        precond=_precond_at(post, None, lam_g, mu_g))
    return full_displacement(post, u_b, u_i), info


def _support(post: Posterior):
    lo = jnp.maximum(post.prior_r1, 0.0)
    return lo, post.prior_r2 - lo


def from_unconstrained(post: Posterior, eta):
    """Free parameters from their unconstrained values, with the log-Jacobian.

    ``phi = r1 + (r2 - r1) sigmoid(eta)`` maps the real line onto the prior support
    ``(r1, r2)`` of each parameter (``r1 >= 0``), so every ``eta`` is a valid parameter.

    Parameters
    ----------
    post : Posterior
    eta : (..., n_free) array

    Returns
    -------
    phi : (..., n_free) array
    log_jac : (...) array
        ``sum log |d phi / d eta|``: add it to a density over ``phi`` to get the density
        over ``eta``.

    Raises
    ------
    ValueError
        ``eta`` not of shape ``(..., n_free)``.
    """
    _check_last_axis("eta", eta, post.n_free, "the unconstrained free elastic parameters")
    lo, width = _support(post)
    phi = lo + width * jax.nn.sigmoid(eta)
    log_jac = jnp.sum(jnp.log(width) + jax.nn.log_sigmoid(eta) + jax.nn.log_sigmoid(-eta), axis=-1)
    return phi, log_jac


def to_unconstrained(post: Posterior, phi):
    """Inverse of :func:`from_unconstrained` (``phi`` ``(..., n_free)`` strictly inside the
    prior support).  Raises ``ValueError`` on ``phi`` not of shape ``(..., n_free)``."""
    _check_last_axis("phi", phi, post.n_free, "the free elastic parameters")
    lo, width = _support(post)
    x = (jnp.asarray(phi) - lo) / width
    return jnp.log(x) - jnp.log1p(-x)


def dense_stiffness(post: Posterior, phi):
    """Dense stiffness ``K`` ``(3N, 3N)``, interior DOFs first (see ``Posterior.dense_index``).

    Memory ``72 N^2`` bytes: meant for meshes up to a few thousand nodes.
    """
    lam_g, mu_g = elastic_groups(post, phi)
    lam_e, mu_e = lam_g[post.group], mu_g[post.group]
    m = lam_e.shape[0]
    ke = (lam_e[:, None, None, None, None] * post.op.klam + mu_e[:, None, None, None, None] * post.op.kmu)
    ke = ke.transpose(0, 1, 3, 2, 4).reshape(m, 144)  # (a, i, b, j) -> rows 3a+i, cols 3b+j
    n_dof = 3 * post.nodes.shape[0]
    return jax.ops.segment_sum(ke.reshape(-1), post.dense_index, num_segments=n_dof * n_dof).reshape(n_dof, n_dof)


def log_normaliser(post: Posterior, phi):
    """``(1/2) log pdet S(lam, mu)``: the exact normaliser of the elastic prior on ``u_b``.

    With the interior at the FE solution, ``exp(-E_r / T_r)`` (Eq. 12) is a Gaussian on the
    boundary displacements with precision ``S / T_r`` (``S`` the Schur complement of ``K`` on
    the boundary DOFs, singular on the six rigid-body modes), whose log-normaliser is
    ``(1/2) log pdet S - ((3 n_b - 6) / 2) log (2 pi T_r)``; the second term is constant.

    Computed from one dense float64 Cholesky factorisation of the stiffness with the
    rigid-body modes of the boundary block lifted, interior DOFs first: ``K_aug = K + c P``,
    ``P = R_b R_b^T`` on the boundary block (``R_b`` orthonormal rigid modes, ``c`` the mean
    of ``diag K_bb``).  Its trailing block of the factor is the Cholesky factor of the Schur
    complement ``S + c P``, and ``det(S + c P) = c^6 pdet S`` because ``P`` projects onto the
    null space of ``S``.  Cost ``(3N)^3 / 3`` flops (about 20 ms at 350 nodes, 0.2-0.3 s at
    900 on a 2-core CPU), differentiable by JAX (the gradient costs about 8x the value).

    Parameters
    ----------
    post : Posterior
    phi : (n_free,) array  positive free parameters

    Returns
    -------
    () array
        ``NaN`` when the factorisation fails (``K`` not positive definite on the complement
        of the rigid modes: non-positive parameters).
    """
    k = dense_stiffness(post, phi)
    nb3 = post.rigid_b.shape[0]
    k_bb = k[-nb3:, -nb3:]
    c = jax.lax.stop_gradient(jnp.mean(jnp.diag(k_bb)))  # any c > 0: the result does not depend on it
    k = k.at[-nb3:, -nb3:].add(c * post.rigid_b @ post.rigid_b.T)
    chol = jnp.linalg.cholesky(0.5 * (k + k.T))
    return jnp.sum(jnp.log(jnp.diag(chol)[-nb3:])) - 3.0 * jnp.log(c)


def add_normaliser(logp, log_norm):
    """``logp + log_norm``, ``-inf`` where either is not finite (a failed factorisation gives
    a NaN normaliser: that position is rejected like any other hard-constraint violation)."""
    return jnp.where(jnp.isfinite(logp) & jnp.isfinite(log_norm), logp + log_norm, -jnp.inf)

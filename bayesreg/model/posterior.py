"""The posterior of paper Eqs. 8-12 over boundary displacements and Lamé parameters.

``log p(u_b, lam, mu | m) = -E_s(u) / T_s - E_r(u; lam, mu) / T_r + log p(lam) + log p(mu)``
(+ const), where ``u`` on the interior nodes solves ``K_ii u_i = -K_ib u_b`` (Sec. 3.3:
only boundary nodes are sampled), ``E_s`` is the SSD of Eq. 1 (:mod:`bayesreg.model.similarity`)
and ``E_r`` the strain energy of Eqs. 2-3.  The Lamé parameters live on groups of
elements, some of them possibly fixed, with scaled Beta priors
(:mod:`bayesreg.model.parameters`).

Hard constraints (Sec. 3.2) give ``log p = -inf``: a node inside the forbidden (skull)
region or outside the image (:mod:`bayesreg.mesh.constraints`), a parameter outside its prior
support or non-positive, an inverted element in the deformed mesh.  A CG solve that does
not converge also gives ``-inf`` (the proposal is rejected) and is flagged in :class:`Aux`
so that the driver counts and reports it: it is never silently accepted.  An optional
smooth barrier (``barrier_mm`` of :func:`build_posterior`) bends the log-density down near
the skull for gradient kernels; the hard constraint stays, and a node at the barrier's own
singularity (:func:`bayesreg.mesh.constraints.skull_barrier`) is forbidden too.

Position layout: one flat float64 vector ``theta = [u_b.ravel(), phi]`` with ``u_b``
node-major (``3*i + axis``, mm) and ``phi`` the free elastic parameters; with a model
discrepancy (:class:`Discrepancy`) ``theta = [u_b.ravel(), d.ravel(), phi]``, ``d``
``(n_i, 3)`` mm the interior nodes' deviation from the FE solve, so that
``u_i = -K_ii^-1 K_ib u_b + d``; with a low-rank discrepancy ``theta = [u_b.ravel(), c,
phi]``, ``c`` ``(r,)`` the coordinates of ``d`` in its basis (:func:`discrepancy_of`); an
orthogonal discrepancy displaces the interior by ``P d`` (:func:`orthogonal_discrepancy`).  The
exact normaliser of the elastic prior, ``(1/2) log pdet S(lam, mu)``, is
:func:`log_normaliser` (:mod:`bayesreg.fem.normaliser`).
"""

from __future__ import annotations

from functools import partial
from typing import NamedTuple

import jax
import jax.numpy as jnp
from jax.scipy.linalg import cho_solve
import numpy as np

from bayesreg._checks import check_last_axis, check_shape
from bayesreg.mesh.constraints import (
    SkullConstraint, element_volumes, points_forbidden, skull_barrier, skull_constraint,
    with_barrier)
from bayesreg.fem.element import (
    element_strain_energy, interior_solver, shape_gradients, stiffness_matrix)
from bayesreg.data.images import check_image
from bayesreg.jaxconfig import require_x64
from bayesreg.mesh.tetmesh import Mesh
from bayesreg.fem.normaliser import (
    NormaliserData, Surrogate, build_surrogate, dense_stiffness, log_pdet_schur, log_pdet_sparse,
    normaliser_data, surrogate_log_pdet, trace_inverse_interior)
from bayesreg.model.parameters import BetaPriors, ParamLayout, beta_priors
from bayesreg.model.parameters import log_prior as prior_log_density
from bayesreg.fem.preconditioners import (
    DENSE_MAX_DOFS, DensePreconditioner, SpectralPreconditioner, dense_preconditioner,
    spectral_preconditioner)
from bayesreg.model.lncc import LNCCTerm
from bayesreg.model.similarity import SSDTerm
from bayesreg.fem.solver import SolveInfo, interior_map_blocks, solve_interior_blocks
from bayesreg.fem.stiffness import (
    ElasticOperator, GroupBlocks, build_operator, ell_dense, ell_matvec, ell_sparse, group_blocks)

__all__ = [
    "Posterior",
    "Aux",
    "Discrepancy",
    "discrepancy_of",
    "discrepancy_map",
    "node_slots",
    "orthogonal_discrepancy",
    "discrepancy_log_prior",
    "discrepancy_rate",
    "discrepancy_stiffness",
    "discrepancy_precision_draw",
    "discrepancy_mixture_log_ratio",
    "shift_discrepancy",
    "data_log_likelihood",
    "similarity_curvature",
    "interior_map_and_precision",
    "smoothest_modes",
    "nodal_displacement",
    "build_posterior",
    "with_skull_barrier",
    "log_density",
    "log_density_condensed",
    "condensation",
    "preconditioner",
    "split_position",
    "elastic_groups",
    "full_displacement",
    "energies",
    "stiffness_blocks",
    "solve_position",
    "log_normaliser",
    "log_normaliser_dense",
    "normaliser_surrogate",
    "surrogate_normaliser",
    "rigid_log_prior",
    "similarity_log_likelihood",
    "similarity_weight",
    "prior_precision",
    "MAX_GROUPED",
    "SCOPES",
]


#: At most this many parameter groups get shared per-group stiffness blocks
#: (:class:`bayesreg.fem.stiffness.GroupBlocks`, ``144 G n_i (S_i + S_b)`` bytes); more (the
#: per-element model) assemble ``K`` from the elements at each evaluation.
MAX_GROUPED = 16

#: Names (:func:`jax.named_scope`) of the parts of :func:`log_density`, carried into the
#: compiled program's metadata (no cost at run time), so that a profile of the compiled
#: step can attribute its time to them (``benchmarks/profile_step.py``).
SCOPES = {
    "stiffness": "bayesreg_stiffness",  # K_ii, K_ib blocks at the position's lam, mu
    "solve": "bayesreg_solve",  # the interior CG solve
    "similarity": "bayesreg_similarity",  # E_s at the Gauss points (Eq. 1)
    "strain_energy": "bayesreg_strain_energy",  # E_r (Eqs. 2-7)
    "constraints": "bayesreg_constraints",  # prior support, inverted elements, skull, barrier
}


class Discrepancy(NamedTuple):
    """A model discrepancy on the interior nodes (Kennedy and O'Hagan 2001).

    The interior displacement is the FE solve plus a deviation ``d`` ``(n_i, 3)`` mm that the
    chains sample with the displacement:  ``u_i = -K_ii^-1 K_ib u_b + d``.  Its prior is
    ``N(0, T_d K0_ii^-1)``, ``K0_ii`` the interior block of ``K`` at fixed reference
    parameters (the chains' central start, ``model.initial_*``; it does not move with
    ``lam, mu``, so ``d`` carries no information about them), with the precision
    ``tau = 1 / T_d`` under a Gamma(a, b) prior integrated out: a multivariate Student t,

    ``log p(d) = -(a + 3 n_i / 2) log(1 + q / b) + const``,  ``q = d^T K0_ii d / 2``

    (``df = 2a``, shape ``(b / a) K0_ii^-1``).  Its amplitude is learned from the images:
    ``tau | d ~ Gamma(a + 3 n_i / 2, b + q)``.  The elastic parameters keep what the FE model
    explains (``u_b`` through the Schur complement, ``u_i`` through the solve); what it
    cannot make (a bump, real brain shift) goes into ``d``.

    Low rank (``basis`` given): ``d = V c`` with ``V`` the ``r`` eigenvectors of ``K0_ii``
    of its smallest eigenvalues ``Lambda`` (the smoothest deviations, the leading terms of
    the Karhunen-Loeve expansion of the same Gaussian), ``c`` ``(r,)`` sampled:
    ``q = c^T Lambda c / 2`` and ``3 n_i`` becomes ``r`` above.  A smooth shift stays
    representable while the interior's finer pattern still follows the FE solve, which is
    what identifies the elastic parameters.

    Orthogonal (``sensitivities`` given; Plumlee 2017, *Bayesian calibration with an
    orthogonal discrepancy*): the displacement takes the part of the sampled deviation that
    is ``K0_ii``-orthogonal to the FE interior's sensitivities ``S = d(H(phi) u_b) / d log
    phi`` ``(3 n_i, k)`` (at ``phi_ref`` and a fixed ``u_b``, :func:`orthogonal_discrepancy`):
    ``u_i = H(phi) u_b + P d``, ``P = I - S G^-1 S^T K0_ii``, ``G = S^T K0_ii S``.  So ``d``
    cannot mimic a change of the elastic parameters, and the interior's components along
    ``S`` are the FE model's alone: the parameters are read from them whatever the
    discrepancy's spread elsewhere.  The prior above stays on the sampled ``d`` (``P`` is
    ``K0_ii``-orthogonal, so ``q`` splits into the displacing part's and ``k`` coordinates
    that displace nothing, which keep the density proper).

    Attributes
    ----------
    k_ii : tuple of (R_k, S_k, 3, 3) arrays
        Sliced ELL blocks of ``K0_ii`` (the layout of :attr:`Posterior.op`).
    shape : ()
        ``a + 3 n_i / 2`` (``a + r / 2`` low rank).
    rate : ()
        ``b`` ([lam] mm^3, the unit of the strain energy): the floor of ``T_d``, which
        is about ``2 b / (3 n_i)`` (``2 b / r``) where the images ask for no discrepancy
        (:func:`discrepancy_rate`).
    basis : (3 n_i, r) array or None
        Low rank: the orthonormal eigenvectors ``V`` (interior DOFs ``3 i + axis``).
    eigenvalues : (r,) array or None
        Low rank: ``Lambda``, ascending ([lam] mm).
    sensitivities : (3 n_i, k) array or None
        Orthogonal: ``S`` (mm per unit ``log phi``, interior DOFs ``3 i + axis``).
    dual : (3 n_i, k) array or None
        Orthogonal: ``K0_ii S G^-1``, so that ``P d = d - S (dual^T d)``.
    """

    k_ii: tuple
    shape: jax.Array
    rate: jax.Array
    basis: jax.Array | None = None
    eigenvalues: jax.Array | None = None
    sensitivities: jax.Array | None = None
    dual: jax.Array | None = None


class Posterior(NamedTuple):
    """Static data of the log-density (a pytree of arrays; see module docstring).

    Attributes
    ----------
    op : ElasticOperator
        The interior rows of ``K`` (:mod:`bayesreg.fem.stiffness`).
    nodes : (N, 3)
        World mm.
    tets : (M, 4) int
    grads : (M, 4, 3)
        Shape-function gradients, 1/mm.
    volumes : (M,)
        mm^3.
    perm : (N,) int
        ``u = concat(u_b, u_i)[perm]`` scatters boundary/interior blocks to node order.
    boundary : (n_b,) int
    group : (M,) int
        Parameter group of each element.
    base : (2G,)
        ``[lam_0..lam_G-1, mu_0..mu_G-1]`` with the fixed values in place.
    free_index : (n_free,) int
        Position in ``base`` of each free parameter.
    prior : BetaPriors
        Scaled Beta prior of each free parameter.
    phi_ref : (n_free,)
        A valid parameter vector, substituted in the solve when a proposal leaves the
        support (its log-density is ``-inf`` anyway; this keeps ``K_ii`` SPD under vmap).
    similarity : SSDTerm or LNCCTerm
        The similarity term ``E_s`` (:mod:`bayesreg.model.similarity`: SSD, the paper's;
        :mod:`bayesreg.model.lncc`: local normalised cross-correlation).
    skull : SkullConstraint
        The hard constraint and the barrier (:mod:`bayesreg.mesh.constraints`).
    inv_t_s, inv_t_r : ()
        ``1 / T_s`` and ``1 / T_r``.
    t_s_shape, t_s_rate : ()
        The similarity temperature as a parameter (``build_posterior(t_s_prior=(a, b))``):
        its precision ``tau = 1 / T_s`` with a Gamma(a, b) prior, integrated out, so that
        ``exp(-E_s / T_s)`` becomes ``(1 + E_s / b)^-(a + n_q / 2)`` (``n_q`` quadrature
        points, each an observation of variance ``1 / (2 w_q tau)``; Risholm et al. 2013);
        ``t_s_shape = a + n_q / 2``.  ``t_s_shape = 0``: ``T_s`` fixed at ``1 / inv_t_s``.
    inv_rigid_var : ()
        ``1 / (n_b sigma^2)``: precision of each coefficient ``a_k = r_k . u_b`` of ``u_b``
        on the six orthonormal rigid-body modes ``r_k`` (:attr:`NormaliserData.rigid_b`), a
        proper Gaussian prior of rms boundary displacement ``sigma`` mm along each mode
        (``build_posterior(rigid_sd=sigma)``); 0: flat along them, as the paper (the
        elastic prior does not see rigid motion).
    normaliser : NormaliserData
        What :func:`log_normaliser` needs (:mod:`bayesreg.fem.normaliser`).
    unit_blocks : GroupBlocks or None
        Per-group unit blocks of ``K_ii``, ``K_ib`` when there are at most
        ``MAX_GROUPED`` groups (uniform and tissue models), else ``None`` (per-element
        model: the blocks are assembled from the elements); see :func:`stiffness_blocks`.
    spectral : SpectralPreconditioner or None
        The exact CG preconditioner of a one-group model at every ``lam, mu``
        (``build_posterior(spectral=True)``), shared by all chains; :func:`log_density`
        uses it when no other preconditioner is given.
    discrepancy : Discrepancy or None
        The model discrepancy on the interior nodes (``build_posterior(discrepancy=...)``),
        or ``None``: the paper's model, the interior at the FE solve.
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
    prior: BetaPriors
    phi_ref: jax.Array
    similarity: SSDTerm | LNCCTerm
    skull: SkullConstraint
    inv_t_s: jax.Array
    inv_t_r: jax.Array
    normaliser: NormaliserData
    unit_blocks: GroupBlocks | None = None
    spectral: SpectralPreconditioner | None = None
    inv_rigid_var: jax.Array | float = 0.0
    t_s_shape: jax.Array | float = 0.0
    t_s_rate: jax.Array | float = 1.0
    discrepancy: Discrepancy | None = None

    @property
    def n_boundary(self) -> int:
        return self.boundary.shape[0]

    @property
    def n_discrepancy(self) -> int:
        """Entries of ``theta`` that the discrepancy takes: ``3 n_i``, ``r`` low rank
        (:class:`Discrepancy`), 0 without one."""
        if self.discrepancy is None:
            return 0
        basis = self.discrepancy.basis
        return 3 * self.op.n_interior if basis is None else basis.shape[1]

    @property
    def n_displacement(self) -> int:
        """Length of ``theta``'s displacement block: ``3 n_b`` (+ :attr:`n_discrepancy`)."""
        return 3 * self.n_boundary + self.n_discrepancy

    @property
    def n_free(self) -> int:
        return self.free_index.shape[0]

    @property
    def dim(self) -> int:
        return self.n_displacement + self.n_free

    @property
    def barrier_width(self) -> float:
        """Width (mm) of the skull barrier, 0 = off."""
        return float(self.skull.barrier_width)


class Aux(NamedTuple):
    """By-products of one log-density evaluation.

    Attributes
    ----------
    interior : (n_i, 3)
        Interior displacements of the FE solve (the next warm start), mm; a model
        discrepancy, where there is one, is not in them (:func:`nodal_displacement`).
    solve : SolveInfo
    e_s, e_r : ()
        Similarity and strain energies.
    """

    interior: jax.Array
    solve: SolveInfo
    e_s: jax.Array
    e_r: jax.Array


def build_posterior(
    mesh: Mesh,
    similarity: SSDTerm | LNCCTerm,
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
    rigid_sd: float | None = None,
    t_s_prior: tuple[float, float] | None = None,
    discrepancy: tuple[float, float] | None = None,
) -> Posterior:
    """Assemble :class:`Posterior` from a mesh, the similarity term and the parameter layout.

    Parameters
    ----------
    mesh : Mesh
    similarity : SSDTerm or LNCCTerm
        The similarity term of the mesh and the images:
        :func:`bayesreg.model.similarity.build_ssd` (the paper's SSD) or
        :func:`bayesreg.model.lncc.build_lncc`.
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
        Width (mm) of the optional smooth skull barrier
        (:func:`bayesreg.mesh.constraints.skull_barrier`); 0 = off.
    spectral : bool
        Build :attr:`Posterior.spectral` (one parameter group and ``3 n_i <=
        DENSE_MAX_DOFS`` only; ignored otherwise).
    rigid_sd : float, optional
        rms boundary displacement (mm) of the proper prior along the rigid-body modes
        (:attr:`Posterior.inv_rigid_var`); ``None``: flat along them.
    t_s_prior : (shape, rate), optional
        Gamma prior of ``1 / T_s``, integrated out (:attr:`Posterior.t_s_shape`).
    discrepancy : (a, floor_mm) or (a, floor_mm, modes), optional
        Sample a model discrepancy on the interior nodes (:class:`Discrepancy`): the Gamma
        prior's shape ``a`` of ``1 / T_d`` and the rms per node (mm) of ``d`` at the floor
        of ``T_d`` (:func:`discrepancy_rate`), with ``K0_ii`` at ``phi_ref``; ``modes``
        (an int, or ``None``: every interior DOF) spans ``d`` by that many of ``K0_ii``'s
        smoothest eigenmodes (:func:`smoothest_modes`).  ``None``: the paper's model.

    Returns
    -------
    Posterior

    Raises
    ------
    ValueError
        Non-positive temperatures; a ``prior`` that is not a dict with an entry for each
        kind of free parameter (``"lam"``, ``"mu"``), each one ``(A, B, r1, r2)`` or one
        such tuple per group, with finite ``A, B > 0`` and ``0 <= r1 < r2 < inf``;
        ``phi_ref`` not of shape ``(n_free,)`` or not strictly inside its support (NaN
        included); ``forbidden`` not a 3D :class:`~bayesreg.data.images.Image` with a finite
        invertible affine; a negative barrier width; ``rigid_sd`` not finite and > 0;
        ``t_s_prior`` or ``discrepancy``'s first two not finite numbers > 0; its ``modes``
        not an integer >= 1; ``discrepancy`` on a mesh without interior nodes.
    RuntimeError
        JAX runs in float32 (call :func:`bayesreg.configure_jax` first).

    Examples
    --------
    The posterior of a small synthetic problem (a box mesh over a random image):

    >>> import numpy as np
    >>> import bayesreg
    >>> from bayesreg.data.images import Image
    >>> from bayesreg.mesh.tetmesh import Mesh, boundary_nodes, orient_tets
    >>> from bayesreg.model.parameters import ParamLayout
    >>> from bayesreg.model.posterior import build_posterior
    >>> from bayesreg.model.similarity import build_ssd
    >>> bayesreg.configure_jax()
    >>> nodes = np.array([[0, 0, 0], [20, 0, 0], [0, 20, 0], [0, 0, 20], [20, 20, 20]], float) + 10
    >>> tets = orient_tets(nodes, np.array([[0, 1, 2, 3], [1, 2, 3, 4]]))
    >>> mesh = Mesh(nodes, tets, np.zeros(2, np.int64), boundary_nodes(tets))
    >>> img = Image(np.random.default_rng(0).random((40, 40, 40)), np.eye(4))
    >>> skull = Image(np.zeros((40, 40, 40), np.uint8), np.eye(4))
    >>> layout = ParamLayout(("all",), (("lam", 0),), (("mu", 0, 1.0),))
    >>> post = build_posterior(mesh, build_ssd(nodes, tets, img, img), skull, t_s=1.0, t_r=1.0,
    ...                        layout=layout, element_group=np.zeros(2, np.int64),
    ...                        prior={"lam": (1, 1, 0, 100)}, phi_ref=[5.0])
    >>> post.dim  # 3 coordinates of each of the 5 boundary nodes, and lam
    16
    """
    require_x64("build_posterior")
    if not (t_s > 0 and t_r > 0 and np.isfinite(t_s) and np.isfinite(t_r)):
        raise ValueError(f"temperatures must be finite and > 0, got T_s={t_s}, T_r={t_r}")
    if rigid_sd is not None and not (np.isfinite(rigid_sd) and rigid_sd > 0):
        raise ValueError(f"rigid_sd must be finite and > 0 (mm) or None, got {rigid_sd}")
    if t_s_prior is not None and not (len(t_s_prior) == 2 and all(
            np.isfinite(v) and v > 0 for v in t_s_prior)):
        raise ValueError(f"t_s_prior must be (shape, rate), both finite and > 0, got {t_s_prior}")
    if t_s_prior is not None and similarity.kind != "ssd":
        raise ValueError(f"t_s_prior (the SSD's noise precision integrated out) needs the SSD term, "
                         f"got the {similarity.kind} term")
    forbidden = check_image(forbidden, "forbidden")
    n_groups = len(layout.group_names)
    base = np.ones(2 * n_groups)
    for p, g, v in layout.fixed:
        if v <= 0:
            raise ValueError(f"fixed {p}_{layout.group_names[g]} must be > 0, got {v}")
        base[g + (n_groups if p == "mu" else 0)] = v
    free_index = np.array([g + (n_groups if p == "mu" else 0) for p, g in layout.free], int)
    priors = beta_priors(prior, layout)
    r1, r2 = np.asarray(priors.r1), np.asarray(priors.r2)
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
    skull = skull_constraint(forbidden, barrier_mm=barrier_mm, nodes=mesh.nodes)
    op, interior = build_operator(mesh.nodes, mesh.tets, mesh.boundary)
    n_b, n_i = len(mesh.boundary), len(interior)
    perm = np.empty(len(mesh.nodes), np.int64)
    perm[mesh.boundary] = np.arange(n_b)
    perm[interior] = n_b + np.arange(n_i)
    grads, vol = shape_gradients(mesh.nodes, mesh.tets)
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
        prior=priors,
        phi_ref=jnp.asarray(phi_ref),
        similarity=similarity,
        skull=skull,
        inv_t_s=jnp.asarray(1.0 / t_s),
        inv_t_r=jnp.asarray(1.0 / t_r),
        normaliser=normaliser_data(mesh.nodes, mesh.tets, mesh.boundary, perm, op.klam, op.kmu,
                                   element_group, n_groups, grouped=n_groups <= MAX_GROUPED),
        unit_blocks=group_blocks(op, element_group, n_groups) if n_groups <= MAX_GROUPED else None,
        inv_rigid_var=jnp.asarray(0.0 if rigid_sd is None else 1.0 / (n_b * rigid_sd**2)),
        t_s_shape=jnp.asarray(0.0 if t_s_prior is None
                              else t_s_prior[0] + 0.5 * similarity.n_observations),
        t_s_rate=jnp.asarray(1.0 if t_s_prior is None else float(t_s_prior[1])),
    )
    if spectral and n_groups == 1 and 3 * n_i <= DENSE_MAX_DOFS:
        ub = post.unit_blocks
        post = post._replace(spectral=spectral_preconditioner(op, *ub.group(0)))
    if discrepancy is not None:
        if not (len(discrepancy) in (2, 3)
                and all(np.isfinite(v) and v > 0 for v in discrepancy[:2])):
            raise ValueError(f"discrepancy must be (shape, floor_mm[, modes]), shape and floor_mm "
                             f"finite and > 0, got {discrepancy}")
        modes = discrepancy[2] if len(discrepancy) == 3 else None
        if modes is not None and not (int(modes) == modes and modes >= 1):
            raise ValueError(f"the discrepancy's modes must be an integer >= 1, got {modes}")
        if n_i == 0:
            raise ValueError("a model discrepancy on the interior nodes needs interior nodes "
                             "(model.interior: solve, a mesh with interior nodes)")
        lam0, mu0 = elastic_groups(post, post.phi_ref)
        a, floor_mm = (float(v) for v in discrepancy[:2])
        k_ii = stiffness_blocks(post, lam0, mu0)[0]
        basis = eigenvalues = None
        if modes is not None:
            eigenvalues, basis = smoothest_modes(k_ii, post.op, int(modes))
        dofs = 3 * n_i if basis is None else basis.shape[1]
        post = post._replace(discrepancy=Discrepancy(
            k_ii, jnp.asarray(a + 0.5 * dofs),
            jnp.asarray(discrepancy_rate(post, a, floor_mm, eigenvalues)),
            None if basis is None else jnp.asarray(basis),
            None if eigenvalues is None else jnp.asarray(eigenvalues)))
    return post


def smoothest_modes(k_ii, op: ElasticOperator, modes: int) -> tuple[np.ndarray, np.ndarray]:
    """The ``modes`` eigenpairs of ``K_ii`` (sliced ELL blocks ``k_ii`` in ``op``'s layout)
    of its smallest eigenvalues: the smoothest interior deviations (Dirichlet on the
    boundary nodes), the leading Karhunen-Loeve modes of ``N(0, K_ii^-1)``.  Host code.

    Dense ``eigh`` up to :data:`~bayesreg.fem.preconditioners.DENSE_MAX_DOFS` interior DOFs,
    else ARPACK in shift-invert mode about 0 (:func:`scipy.sparse.linalg.eigsh`).  ``modes``
    is capped at ``3 n_i``.

    Returns
    -------
    eigenvalues : (r,) ndarray
        Ascending, > 0 ([lam] mm).
    basis : (3 n_i, r) ndarray
        Orthonormal eigenvectors, interior DOF order ``3 i + axis``.

    Raises
    ------
    ValueError
        ``K_ii`` not positive definite (an eigenvalue <= 0).
    """
    import scipy.linalg as sla
    import scipy.sparse as sp
    import scipy.sparse.linalg as spla

    n = 3 * op.n_interior
    r = min(int(modes), n)
    if n <= DENSE_MAX_DOFS or r >= n - 1:
        dense = np.asarray(ell_dense(k_ii, op.cols_ii, op.row_ii, op.n_interior))
        vals, vecs = sla.eigh(0.5 * (dense + dense.T), subset_by_index=[0, r - 1])
    else:
        k = ell_sparse(k_ii, op.cols_ii, op.row_ii, op.n_interior)
        vals, vecs = spla.eigsh(sp.csc_matrix(0.5 * (k + k.T)), k=r, sigma=0.0, which="LM")
        order = np.argsort(vals)
        vals, vecs = vals[order], vecs[:, order]
    if not np.all(vals > 0):
        raise ValueError(f"K_ii is not positive definite (smallest eigenvalue {vals.min():.3g})")
    return vals, vecs


def discrepancy_rate(post: Posterior, shape: float, floor_mm: float, eigenvalues=None) -> float:
    """The Gamma prior's rate ``b`` of ``1 / T_d`` (:class:`Discrepancy`) that puts the floor of
    ``T_d`` at ``floor_mm`` rms per interior node.

    Where the images ask for no discrepancy (``q -> 0``), ``1 / T_d`` has posterior mean
    ``(a + 3 n_i / 2) / b``; under ``N(0, T K0_ii^-1)`` the mean squared norm of ``d`` per
    node is ``T tr(K0_ii^-1) / n_i`` (:func:`bayesreg.fem.normaliser.trace_inverse_interior`,
    exact), so ``b = (a + 3 n_i / 2) floor_mm^2 n_i / tr(K0_ii^-1)``, ``K0_ii`` at
    :attr:`Posterior.phi_ref`.  Low rank (``eigenvalues`` ``(r,)`` of the kept modes):
    ``b = (a + r / 2) floor_mm^2 n_i / sum(1 / eigenvalues)``.

    Returns
    -------
    float
        ``b`` in [lam] mm^3.
    """
    n_i = post.op.n_interior
    if eigenvalues is not None:
        ev = np.asarray(eigenvalues)
        return (shape + 0.5 * len(ev)) * floor_mm**2 * n_i / float(np.sum(1.0 / ev))
    lam0, mu0 = elastic_groups(post, post.phi_ref)
    trace = trace_inverse_interior(post.normaliser, post.op.klam, post.op.kmu, lam0, mu0, post.group)
    return (shape + 1.5 * n_i) * floor_mm**2 * n_i / trace


def with_skull_barrier(post: Posterior, barrier_mm: float) -> Posterior:
    """``post`` with a skull barrier of width ``barrier_mm`` (mm; 0 = off) in place of its own
    (:func:`bayesreg.mesh.constraints.with_barrier`).

    Raises
    ------
    ValueError
        ``barrier_mm`` negative or not finite.
    """
    return post._replace(skull=with_barrier(post.skull, barrier_mm))


def _check_theta(post: Posterior, theta):
    disc, name = "", ""
    if post.discrepancy is not None:
        low = post.discrepancy.basis is not None
        disc = f" + {post.n_discrepancy} discrepancy {'coordinates' if low else 'DOFs'}"
        name = "c, " if low else "d.ravel(), "
    check_shape("theta", theta, (post.dim,),
                 f"[u_b.ravel(), {name}phi]: 3 * {post.n_boundary} "
                 f"boundary DOFs{disc} + {post.n_free} free parameters")


def split_position(post: Posterior, theta):
    """``theta`` ``(dim,)`` -> ``u_b`` ``(n_b, 3)`` mm and ``phi`` ``(n_free,)``
    (the discrepancy, if any: :func:`discrepancy_of`).

    Raises
    ------
    ValueError
        ``theta`` not of shape ``(dim,)`` (one position; map batches with ``vmap``).
    """
    _check_theta(post, theta)
    nb3 = 3 * post.n_boundary
    return theta[:nb3].reshape(-1, 3), theta[post.n_displacement:]


def node_slots(post: Posterior) -> tuple[np.ndarray, np.ndarray]:
    """Mesh node indices of the sampled boundary nodes and of the solved interior nodes, in
    the order of ``u_b`` and ``u_i`` (the inverse of :attr:`Posterior.perm`).  Host arrays."""
    perm = np.asarray(post.perm)  # full[j] = concat(u_b, u_i)[perm[j]]
    node = np.empty_like(perm)
    node[perm] = np.arange(len(perm))
    return node[:post.n_boundary], node[post.n_boundary:]


def _discrepancy(post: Posterior, what: str) -> Discrepancy:
    """``post``'s discrepancy, or ``ValueError`` naming ``what`` needs one."""
    if post.discrepancy is None:
        raise ValueError(f"{what} needs a posterior with a model discrepancy")
    return post.discrepancy


def discrepancy_of(post: Posterior, theta, *, projected: bool = True):
    """The model discrepancy ``d`` ``(n_i, 3)`` mm of a position ``theta`` ``(..., dim)``
    (batches allowed; low rank ``d = V c``), or ``None`` without one (:class:`Discrepancy`).

    An orthogonal discrepancy gives the part that displaces the interior, ``P d``; with
    ``projected=False`` the sampled ``d`` itself, which the prior sees."""
    if post.discrepancy is None:
        return None
    d = theta[..., 3 * post.n_boundary:post.n_displacement]
    if post.discrepancy.basis is not None:
        d = d @ post.discrepancy.basis.T
    if projected and post.discrepancy.sensitivities is not None:
        disc = post.discrepancy
        d = d - (d @ disc.dual) @ disc.sensitivities.T
    return d.reshape(d.shape[:-1] + (-1, 3))


def discrepancy_map(post: Posterior) -> np.ndarray:
    """The linear map ``M`` ``(3 n_i, n_discrepancy)`` from the discrepancy's entries of
    ``theta`` to the interior displacement it adds (:func:`discrepancy_of`): the identity,
    ``V`` low rank, ``P`` or ``P V`` orthogonal.  Dense host array, for the Gauss-Newton
    precision and the collapsed moves' Gaussian conditional.

    Raises
    ------
    ValueError
        A posterior without a discrepancy.
    """
    disc = _discrepancy(post, "the discrepancy's map")
    m = np.eye(3 * post.op.n_interior) if disc.basis is None else np.asarray(disc.basis)
    if disc.sensitivities is not None:
        m = m - np.asarray(disc.sensitivities) @ (np.asarray(disc.dual).T @ m)
    return m


def orthogonal_discrepancy(post: Posterior, u_b) -> Posterior:
    """``post`` with its discrepancy made orthogonal to the FE interior's sensitivities to
    the elastic parameters (:class:`Discrepancy`; Plumlee 2017), taken at ``phi_ref`` and
    the boundary displacement ``u_b`` ``(n_b, 3)`` mm (a run's central start).  Host code:
    SciPy's reference assembly and interior solve (:func:`bayesreg.fem.element.stiffness_matrix`,
    :func:`bayesreg.fem.element.interior_solver`: one sparse LU of ``K_ii``); ``S[:, k] = -phi_k K_ii^-1 (dK / dphi_k u)_i`` with ``u`` the FE field.

    Raises
    ------
    ValueError
        ``post`` without a discrepancy; ``u_b`` not ``(n_b, 3)`` or not finite; ``u_b``
        that moves the interior by nothing (no sensitivities to be orthogonal to: a start
        without displacement); more free parameters than a quarter of the interior DOFs
        (per-element parameters).
    """
    disc = _discrepancy(post, "an orthogonal discrepancy")
    u_b = np.asarray(u_b, float)
    check_shape("u_b", u_b, (post.n_boundary, 3), "one row per boundary node")
    if not np.all(np.isfinite(u_b)):
        raise ValueError("an orthogonal discrepancy's sensitivities need a finite u_b")
    n_i, k = post.op.n_interior, post.n_free
    if 4 * k > 3 * n_i:
        raise ValueError(f"an orthogonal discrepancy removes one direction per free parameter: "
                         f"{k} free parameters against {3 * n_i} interior DOFs leave it no "
                         "freedom (use groups of parameters, not one per element)")
    nodes, tets, group = (np.asarray(a) for a in (post.nodes, post.tets, post.group))
    lam_g, mu_g = (np.asarray(a) for a in elastic_groups(post, post.phi_ref))
    solver = interior_solver(stiffness_matrix(nodes, tets, lam_g[group], mu_g[group]),
                             *node_slots(post))
    bd, idf = solver.boundary_dofs, solver.interior_dofs
    u = np.zeros(3 * len(nodes))
    u[bd] = u_b.ravel()
    u[idf] = solver.solve(u_b.ravel())
    g = len(lam_g)
    full = np.asarray(post.base, float).copy()
    full[np.asarray(post.free_index)] = np.asarray(post.phi_ref)
    cols = []
    for j in np.asarray(post.free_index):
        is_lam, gj = j < g, j % g
        on = (group == gj).astype(float)
        dk = stiffness_matrix(nodes, tets, on if is_lam else 0.0 * on, 0.0 * on if is_lam else on)
        cols.append(-full[j] * solver.lu.solve((dk @ u)[idf]))
    s_mat = np.stack(cols, axis=1)
    k0s = np.stack([np.asarray(ell_matvec(disc.k_ii, post.op.cols_ii, post.op.row_ii,
                                          jnp.asarray(c.reshape(-1, 3)))).ravel()
                    for c in s_mat.T], axis=1)
    gram = s_mat.T @ k0s
    scale = np.sqrt(np.abs(np.diag(gram)))
    if not np.all(np.isfinite(gram)) or scale.max() == 0.0 or scale.min() < 1e-12 * scale.max():
        raise ValueError("the FE interior does not move with every free parameter at this u_b "
                         "(an orthogonal discrepancy needs a start that displaces the tissue of "
                         "every group: init.method: mode, or init.start: registration)")
    dual = np.linalg.solve(gram, k0s.T).T
    return post._replace(discrepancy=disc._replace(sensitivities=jnp.asarray(s_mat),
                                                   dual=jnp.asarray(dual)))


def shift_discrepancy(post: Posterior, x, delta):
    """The displacement block ``x`` ``(n_displacement,)`` (``[u_b, d]``, low rank ``[u_b,
    c]``) with the discrepancy moved by ``delta`` ``(n_i, 3)`` mm: ``d + delta`` (low rank
    ``c + V^T delta``, the move's projection on the orthonormal modes).  With ``delta`` the
    FE interior's change, ``H(phi) u_b - H(phi') u_b``, every node's displacement ``u`` stays
    where it was (low rank: its part in the modes' span; orthogonal: its part ``P delta``,
    the sensitivities' directions move).  A shear by a function of ``u_b`` alone:
    volume-preserving, undone by ``-delta``.

    Raises
    ------
    ValueError
        A posterior without a discrepancy, or ``x`` or ``delta`` of another shape.
    """
    _discrepancy(post, "shifting the discrepancy")
    check_shape("x", x, (post.n_displacement,), "the displacement block [u_b, d]")
    check_shape("delta", delta, (post.op.n_interior, 3), "one row per interior node")
    step = delta.reshape(-1)
    if post.discrepancy.basis is not None:
        step = step @ post.discrepancy.basis
    return x.at[3 * post.n_boundary:].add(step)


def discrepancy_log_prior(post: Posterior, d):
    """``-(a + 3 n_i / 2) log(1 + q / b)``, ``q = d^T K0_ii d / 2``: the log prior of the
    discrepancy ``d`` ``(n_i, 3)`` mm up to a constant (:class:`Discrepancy`; 0 without one).
    Low rank: ``-(a + r / 2) log(1 + q / b)`` with ``q = c^T Lambda c / 2``, ``c = V^T d``
    (``d`` in the basis's span, as :func:`discrepancy_of` makes it).

    Returns
    -------
    logp, q : () arrays
    """
    if post.discrepancy is None:
        zero = jnp.zeros(())
        return zero, zero
    disc = post.discrepancy
    if disc.basis is not None:
        c = d.reshape(-1) @ disc.basis
        q = 0.5 * jnp.sum(disc.eigenvalues * c * c)
    else:
        q = 0.5 * jnp.sum(d * ell_matvec(disc.k_ii, post.op.cols_ii, post.op.row_ii, d))
    return -disc.shape * jnp.log1p(q / disc.rate), q


def discrepancy_stiffness(post: Posterior):
    """The discrepancy prior's precision per unit ``1 / T_d``, dense: ``K0_ii``
    ``(3 n_i, 3 n_i)`` (:attr:`Discrepancy.k_ii`), low rank ``diag(Lambda)`` ``(r, r)`` (of
    the coordinates ``c``).

    Raises
    ------
    ValueError
        A posterior without a discrepancy.
    """
    disc = _discrepancy(post, "the discrepancy's stiffness")
    if disc.basis is not None:
        return jnp.diag(disc.eigenvalues)
    return ell_dense(disc.k_ii, post.op.cols_ii, post.op.row_ii, post.op.n_interior)


def discrepancy_precision_draw(post: Posterior, key, d):
    """A draw of the discrepancy's precision ``tau = 1 / T_d`` given ``d`` ``(n_i, 3)`` mm:
    ``Gamma(a + 3 n_i / 2, b + q)`` (``a + r / 2`` low rank; :class:`Discrepancy`), the
    conditional that makes the Student prior of ``d`` a Gaussian scale mixture
    (``d | tau ~ N(0, (tau K0_ii)^-1)``, ``tau ~ Gamma(a, b)``).  ``()`` array, [lam]^-1 mm^-3.

    Raises
    ------
    ValueError
        A posterior without a discrepancy.
    """
    _discrepancy(post, "the discrepancy's precision")
    _, q = discrepancy_log_prior(post, d)
    return jax.random.gamma(key, post.discrepancy.shape) / (post.discrepancy.rate + q)


def discrepancy_mixture_log_ratio(post: Posterior, d, tau):
    """``log N(d; 0, (tau K0_ii)^-1) - log p(d)`` up to a constant in ``d``: ``-tau q + (a +
    3 n_i / 2) log(1 + q / b)`` (:func:`discrepancy_log_prior`), what turns ``log p`` into
    the log-density of the model with ``tau`` given (a scale mixture's component), for
    moves made at a fixed ``tau`` (:func:`discrepancy_precision_draw`).  ``()`` array; 0
    without a discrepancy."""
    if post.discrepancy is None:
        return jnp.zeros(())
    log_p, q = discrepancy_log_prior(post, d)
    return -tau * q - log_p


def data_log_likelihood(post: Posterior, u):
    """The terms of ``log p`` that see the nodal displacement ``u`` ``(N, 3)`` mm alone: the
    similarity (:func:`similarity_log_likelihood`) and the smooth skull barrier (0 without
    one); not the elastic prior, the discrepancy's, or the hard constraints.  ``()``."""
    check_shape("u", u, tuple(post.nodes.shape), "one row per node")
    e_s = post.similarity.energy(u[post.tets])
    return similarity_log_likelihood(post, e_s) + skull_barrier(post.skull, post.nodes + u)[0]


def nodal_displacement(post: Posterior, theta, interior):
    """Every node's displacement ``(N, 3)`` mm of a position ``theta`` ``(dim,)``: ``u_b`` and
    the interior ``interior`` ``(n_i, 3)`` (the FE solve's, as :class:`Aux` returns it) plus
    the discrepancy where the model has one."""
    u_b = split_position(post, theta)[0]
    d = discrepancy_of(post, theta)
    return full_displacement(post, u_b, interior if d is None else interior + d)


@jax.jit
def elastic_groups(post: Posterior, phi):
    """Lamé parameters per group from the free parameters (jitted: called on the host on
    batches of draws, and inlined where it is traced).

    Parameters
    ----------
    post : Posterior
    phi : (..., n_free) array
        (batched draws allowed)

    Returns
    -------
    lam_g, mu_g : (..., G) arrays, the fixed parameters in place

    Raises
    ------
    ValueError
        ``phi`` not of shape ``(..., n_free)``.
    """
    phi = jnp.asarray(phi)
    check_last_axis("phi", phi, post.n_free, "the free elastic parameters")
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
    check_shape("u_b", u_b, (post.n_boundary, 3), "one row per boundary node")
    check_shape("u_i", u_i, (post.op.n_interior, 3), "one row per interior node")
    return jnp.concatenate([u_b, u_i], axis=0)[post.perm]


def stiffness_blocks(post: Posterior, lam_g, mu_g):
    """ELL blocks ``(b_ii, b_ib)`` of ``K_ii``, ``K_ib`` (paper Eqs. 5-7) for per-group
    Lamé parameters ``lam_g``, ``mu_g`` ``(G,)``.

    From the shared per-group unit blocks (:class:`bayesreg.fem.stiffness.GroupBlocks`) when the
    posterior has them, else assembled from the elements
    (:meth:`bayesreg.fem.stiffness.ElasticOperator.blocks`); the two agree to round-off (tested).
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
    check_shape("u", u, tuple(post.nodes.shape), "one row per node")
    check_shape("phi", phi, (post.n_free,), "the free elastic parameters")
    lam_g, mu_g = elastic_groups(post, phi)
    u_e = u[post.tets]
    with jax.named_scope(SCOPES["strain_energy"]):
        e_r = element_strain_energy(post.grads, post.volumes, u_e, lam_g[post.group], mu_g[post.group])
    with jax.named_scope(SCOPES["similarity"]):
        e_s = post.similarity.energy(u_e)
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
        ``[u_b.ravel() (mm), phi]`` (``[u_b.ravel(), d.ravel(), phi]`` with a model
        discrepancy: :class:`Discrepancy`, whose prior is then added).
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

    Examples
    --------
    Two tetrahedra over a smooth image: identical images make ``E_s = 0`` at rest, and a
    rigid translation of every boundary node leaves ``E_r = 0`` while ``E_s`` grows:

    >>> import jax.numpy as jnp, numpy as np
    >>> import bayesreg
    >>> from bayesreg.data.images import Image
    >>> from bayesreg.mesh.tetmesh import Mesh, boundary_nodes, orient_tets
    >>> from bayesreg.model.parameters import ParamLayout
    >>> from bayesreg.model.posterior import build_posterior, log_density
    >>> from bayesreg.model.similarity import build_ssd
    >>> bayesreg.configure_jax()
    >>> i, j, k = np.meshgrid(*[np.arange(40.0)] * 3, indexing="ij")
    >>> img = Image(np.sin(i / 6) + np.cos(j / 7) + k / 40, np.eye(4))
    >>> nodes = np.array([[0, 0, 0], [20, 0, 0], [0, 20, 0], [0, 0, 20], [20, 20, 20]], float) + 10
    >>> tets = orient_tets(nodes, np.array([[0, 1, 2, 3], [1, 2, 3, 4]]))
    >>> mesh = Mesh(nodes, tets, np.zeros(2, np.int64), boundary_nodes(tets))
    >>> post = build_posterior(
    ...     mesh, build_ssd(nodes, tets, img, img), Image(np.zeros((40, 40, 40), np.uint8), np.eye(4)),
    ...     t_s=1.0, t_r=1.0, layout=ParamLayout(("all",), (("lam", 0),), (("mu", 0, 1.0),)),
    ...     element_group=np.zeros(2, np.int64), prior={"lam": (1, 1, 0, 100)}, phi_ref=[5.0])
    >>> interior = jnp.zeros((post.op.n_interior, 3))  # no interior node in this mesh
    >>> lp, aux = log_density(post, jnp.asarray(np.r_[np.zeros(15), 5.0]), interior)
    >>> round(float(aux.e_s), 12), float(aux.e_r)  # (m is stored in float32)
    (0.0, 0.0)
    >>> lp, aux = log_density(post, jnp.asarray(np.r_[np.tile([1.0, 0.0, 0.0], 5), 5.0]), interior)
    >>> bool(aux.e_s > 0), abs(float(aux.e_r)) < 1e-12
    (True, True)
    """
    u_b, phi = split_position(post, theta)
    check_shape("u_i0", u_i0, (post.op.n_interior, 3), "warm start, one row per interior node")
    with jax.named_scope(SCOPES["constraints"]):
        log_prior, in_support = prior_log_density(post.prior, phi)
        phi_solve = jnp.where(in_support, phi, post.phi_ref)
        allowed = in_support & ~jnp.any(points_forbidden(post.skull, post.nodes[post.boundary] + u_b))

    def evaluate(_):
        lam_g, mu_g = elastic_groups(post, phi_solve)
        with jax.named_scope(SCOPES["stiffness"]):
            blocks = stiffness_blocks(post, lam_g, mu_g)
        with jax.named_scope(SCOPES["solve"]):
            u_i, info = solve_interior_blocks(
                post.op, *blocks, u_b, u_i0, rtol=rtol, maxiter=jnp.where(allowed, maxiter, 0),
                precond=_precond_at(post, precond, lam_g, mu_g))
        info = SolveInfo(info.iterations, info.residual, info.converged | ~allowed)
        return _finish(post, theta, u_i, info, phi_solve, allowed, log_prior)

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


def _finish(post: Posterior, theta, u_i, info, phi_solve, in_support, log_prior):
    """Energies, hard constraints and ``log p`` from a position and its interior FE solve
    ``u_i``: ``E_r`` of the FE field, ``E_s`` and the constraints of the displacement with
    the discrepancy (if any), whose prior is added."""
    u_b = split_position(post, theta)[0]
    u_fe = full_displacement(post, u_b, u_i)
    d = discrepancy_of(post, theta)
    log_disc, _ = discrepancy_log_prior(post, discrepancy_of(post, theta, projected=False))
    if d is None:
        e_s, e_r = energies(post, u_fe, phi_solve)
        u = u_fe
    else:  # (the unused halves of each call are compiled away)
        u = full_displacement(post, u_b, u_i + d)
        e_s, e_r = energies(post, u, phi_solve)[0], energies(post, u_fe, phi_solve)[1]
    with jax.named_scope(SCOPES["constraints"]):
        barrier, clear = skull_barrier(post.skull, post.nodes + u)  # clear: of its own wall
        ok = (
            in_support
            & info.converged
            & jnp.all(element_volumes(post.nodes + u, post.tets) > 0)
            & ~jnp.any(points_forbidden(post.skull, post.nodes + u))
            & clear
            & jnp.isfinite(e_s)
            & jnp.isfinite(e_r)
        )
    logp = (similarity_log_likelihood(post, e_s) - e_r * post.inv_t_r + log_prior + barrier
            + rigid_log_prior(post, u_b) + log_disc)
    return jnp.where(ok, logp, -jnp.inf), Aux(u_i, info, e_s, e_r)


def similarity_log_likelihood(post: Posterior, e_s):
    """The similarity term of ``log p`` for an SSD ``e_s`` (paper Eqs. 1, 9): ``-E_s / T_s``,
    or with the temperature integrated out (:attr:`Posterior.t_s_shape` > 0)
    ``-(a + n_q / 2) log(1 + E_s / b)`` (up to a constant)."""
    marginal = post.t_s_shape > 0
    return jnp.where(marginal, -post.t_s_shape * jnp.log1p(e_s / post.t_s_rate),
                     -e_s * post.inv_t_s)


def similarity_weight(post: Posterior, e_s):
    """``d log p / d (-E_s)`` at ``e_s``: ``1 / T_s``, or with the temperature integrated out
    ``(a + n_q / 2) / (b + E_s)``, the posterior mean of ``1 / T_s`` given ``E_s`` (what the
    Gauss-Newton preconditioners scale the similarity's curvature by)."""
    return jnp.where(post.t_s_shape > 0, post.t_s_shape / (post.t_s_rate + e_s), post.inv_t_s)


def rigid_log_prior(post: Posterior, u_b):
    """``-(1/2) inv_rigid_var ||R_b^T u_b||^2``: the log prior of ``u_b`` ``(n_b, 3)`` mm along
    the rigid-body modes, up to a constant (0 when the posterior is flat along them;
    :attr:`Posterior.inv_rigid_var`)."""
    a = post.normaliser.rigid_b.T @ u_b.reshape(-1)
    return -0.5 * post.inv_rigid_var * jnp.sum(a * a)


def condensation(post: Posterior, theta):
    """Dense interior map ``H(phi)`` ``(3 n_i, 3 n_b)`` at the parameters of ``theta``
    (:func:`bayesreg.fem.solver.interior_map_blocks` of :func:`stiffness_blocks`); the cache of
    :func:`log_density_condensed`."""
    _, phi = split_position(post, theta)
    _, in_support = prior_log_density(post.prior, phi)
    lam_g, mu_g = elastic_groups(post, jnp.where(in_support, phi, post.phi_ref))
    return interior_map_blocks(post.op, *stiffness_blocks(post, lam_g, mu_g), post.n_boundary)


def preconditioner(post: Posterior, theta) -> DensePreconditioner:
    """Dense CG preconditioner ``K_ii(phi)^-1`` (float32) at the parameters of ``theta``
    (:func:`bayesreg.fem.preconditioners.dense_preconditioner`; :attr:`Posterior.phi_ref` when they leave
    the prior support).  Built once per chain and reused while its parameters move: the
    preconditioner of :func:`log_density` (``precond``) at any nearby parameters."""
    _, phi = split_position(post, theta)
    _, in_support = prior_log_density(post.prior, phi)
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
    theta : (dim,) array
        ``[u_b.ravel() (mm), phi]``
    h : (3 n_i, 3 n_b) array
        interior map at ``theta``'s ``phi``

    Returns
    -------
    logp, aux : as :func:`log_density` (``aux.solve`` reports 0 iterations)

    Raises
    ------
    ValueError
        ``theta`` not of shape ``(dim,)`` or ``h`` not ``(3 n_i, 3 n_b)``.
    """
    u_b, phi = split_position(post, theta)
    check_shape("h", h, (3 * post.op.n_interior, 3 * post.n_boundary),
                 "the interior map (3 n_i, 3 n_b) of condensation()")
    log_prior, in_support = prior_log_density(post.prior, phi)
    phi_solve = jnp.where(in_support, phi, post.phi_ref)
    u_i = (h @ u_b.reshape(-1)).reshape(-1, 3)
    finite = jnp.all(jnp.isfinite(u_i))
    info = SolveInfo(jnp.asarray(0), jnp.where(finite, 0.0, jnp.inf), finite)
    return _finish(post, theta, u_i, info, phi_solve, in_support, log_prior)


def solve_position(post: Posterior, theta, u_i0=None, *, rtol=1e-8, maxiter=1000):
    """Full nodal displacement ``(N, 3)`` mm for a position ``(dim,)`` (the discrepancy
    included, if any: :func:`nodal_displacement`), and the solve's
    :class:`~bayesreg.fem.solver.SolveInfo` (host convenience: one jitted program per mesh
    size and tolerance, where running it op by op compiled about 60 small programs)."""
    if u_i0 is None:
        u_i0 = jnp.zeros((post.op.n_interior, 3))
    return _solve_position(post, jnp.asarray(theta), jnp.asarray(u_i0), rtol=float(rtol),
                           maxiter=int(maxiter))


def similarity_curvature(post: Posterior, theta) -> tuple[np.ndarray, np.ndarray]:
    """The nodal displacement at ``theta`` and the similarity's Gauss-Newton curvature there
    (host convenience: NumPy out).

    Parameters
    ----------
    post : Posterior
    theta : (dim,) array
        A position (with its discrepancy, if any).

    Returns
    -------
    u : (N, 3) array
        Every node's displacement (mm): the FE solve (:func:`solve_position`) plus the
        discrepancy.
    curvature : (3N, 3N) array
        ``2 J^T J / T_s`` over the nodal DOFs ``3 node + axis``: ``J`` the Jacobian of the
        similarity's residuals in the nodal displacement (its exact ``gram``), ``1 / T_s``
        :func:`similarity_weight` at ``u``.  What
        :func:`bayesreg.sampling.kernels.target.nodal_laplace_likelihood` linearises with.
    """
    theta = jnp.asarray(theta)
    u = np.asarray(solve_position(post, theta)[0])
    e_s = energies(post, jnp.asarray(u), theta[post.n_displacement:])[0]
    gram = post.similarity.gram(u, np.asarray(post.tets), u.shape[0]).toarray()
    return u, 2.0 * float(similarity_weight(post, e_s)) * gram


@partial(jax.jit, static_argnames=("rtol", "maxiter"))
def _solve_position(post: Posterior, theta, u_i0, *, rtol, maxiter):
    u_b, phi = split_position(post, theta)
    lam_g, mu_g = elastic_groups(post, phi)
    u_i, info = solve_interior_blocks(
        post.op, *stiffness_blocks(post, lam_g, mu_g), u_b, u_i0, rtol=rtol, maxiter=maxiter,
        precond=_precond_at(post, None, lam_g, mu_g))
    return nodal_displacement(post, theta, u_i), info


def log_normaliser(post: Posterior, phi):
    """``(1/2) log pdet S(lam, mu)``: the exact normaliser of the elastic prior on ``u_b``
    (:func:`bayesreg.fem.normaliser.log_pdet_sparse`: two sparse Cholesky factorisations,
    differentiable by selected inversion).

    Parameters
    ----------
    post : Posterior
    phi : (n_free,) array
        Positive free parameters.

    Returns
    -------
    () array
        ``NaN`` for parameters the factorisation must not see (non-positive, non-finite, or
        below :data:`bayesreg.fem.normaliser.SAFE_RATIO` of the largest): such a position is
        rejected.
    """
    lam_g, mu_g = elastic_groups(post, phi)
    return log_pdet_sparse(post.normaliser, post.op.klam, post.op.kmu, lam_g, mu_g, post.group)


def log_normaliser_dense(post: Posterior, phi):
    """:func:`log_normaliser` by the dense reference (one dense Cholesky factorisation of
    ``K``, ``(3N)^3 / 3`` flops: :func:`bayesreg.fem.normaliser.log_pdet_schur`); NaN where it
    fails."""
    return log_pdet_schur(_dense_k(post, phi), post.normaliser.rigid_b)


def normaliser_surrogate(post: Posterior, phi0) -> Surrogate:
    """The smooth surrogate of :func:`log_normaliser` built at the free parameters ``phi0``
    ``(n_free,)`` (:func:`bayesreg.fem.normaliser.build_surrogate`; host code, seconds at the
    paper's size).

    Raises
    ------
    ValueError
        The per-element model (no surrogate), or ``phi0`` where the normaliser fails.
    """
    lam_g, mu_g = (np.asarray(a) for a in elastic_groups(post, jnp.asarray(phi0)))
    free = np.asarray(post.free_index)  # into [lam_g, mu_g]
    bounds = np.tile([0.0, np.inf], (2 * lam_g.shape[0], 1))
    bounds[free, 0], bounds[free, 1] = np.asarray(post.prior.r1), np.asarray(post.prior.r2)
    return build_surrogate(post.normaliser, post.op.klam, post.op.kmu, post.group, lam_g, mu_g,
                           free=[int(i) for i in free], bounds=bounds)


def surrogate_normaliser(post: Posterior, surrogate: Surrogate, phi):
    """The surrogate's value of :func:`log_normaliser` at ``phi`` ``(n_free,)`` (smooth;
    microseconds)."""
    lam_g, mu_g = elastic_groups(post, phi)
    return surrogate_log_pdet(surrogate, lam_g, mu_g)


def _dense_k(post: Posterior, phi):
    """The dense stiffness ``(3N, 3N)`` at ``phi``, interior DOFs first
    (:func:`bayesreg.fem.normaliser.dense_stiffness`)."""
    lam_g, mu_g = elastic_groups(post, phi)
    return dense_stiffness(post.op.klam, post.op.kmu, lam_g[post.group], mu_g[post.group],
                           post.normaliser, 3 * post.nodes.shape[0])


def prior_precision(post: Posterior, phi):
    """Precision of the elastic prior of ``u_b`` given the parameters: ``S(lam, mu) / T_r +
    inv_rigid_var R_b R_b^T``, dense ``(3 n_b, 3 n_b)`` (``S = K_bb - K_bi K_ii^-1 K_ib`` the
    Schur complement of ``K`` on the boundary DOFs, so ``E_r = u_b^T S u_b / 2`` with the
    interior at its FE solution; paper Eq. 12).

    One dense float64 Cholesky factorisation of ``K_ii`` (``(3 n_i)^3 / 3`` flops) and a
    product with ``K_ib``: meant for meshes up to a few thousand nodes; differentiable.

    Parameters
    ----------
    post : Posterior
    phi : (n_free,) array
        Positive free parameters.

    Returns
    -------
    (3 n_b, 3 n_b) array
        DOF order ``3 k + axis`` of the ``k``-th boundary node (:attr:`Posterior.boundary`);
        NaN where the factorisation fails (non-positive parameters).
    """
    return interior_map_and_precision(post, phi)[1]


def interior_map_and_precision(post: Posterior, phi):
    """The interior map ``H`` ``(3 n_i, 3 n_b)`` (``u_i = H u_b`` solves ``K_ii u_i = -K_ib
    u_b``, :func:`condensation`) and :func:`prior_precision` ``(3 n_b, 3 n_b)`` at ``phi``
    ``(n_free,)``, from one dense Cholesky factorisation of ``K_ii``; NaN where it fails."""
    k = _dense_k(post, phi)
    ni3 = k.shape[0] - 3 * post.n_boundary
    k_ii, k_ib, k_bb = k[:ni3, :ni3], k[:ni3, ni3:], k[ni3:, ni3:]
    chol = jnp.linalg.cholesky(0.5 * (k_ii + k_ii.T))
    x = cho_solve((chol, True), k_ib)
    schur = k_bb - k_ib.T @ x
    rigid = post.normaliser.rigid_b
    prec = post.inv_t_r * schur + post.inv_rigid_var * rigid @ rigid.T
    return -x, 0.5 * (prec + prec.T)

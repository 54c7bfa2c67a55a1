"""A plain NumPy/SciPy implementation of the posterior and of the paper's MH step.

It is the yardstick of the benchmark (``benchmarks/run.py``): the same unnormalised log
posterior as :func:`bayesreg.model.posterior.log_density`, written the way one would without JAX:

* ``K`` (paper Eq. 7) is linear in the per-group Lamé parameters, so the unit matrices of
  every group are assembled once (SciPy sparse, one common sparsity pattern) and ``K`` is a
  weighted sum of their data arrays;
* the interior displacements solve ``K_ii u_i = -K_ib u_b`` with a sparse direct solver
  (:func:`scipy.sparse.linalg.splu`: SuperLU with the minimum-degree ordering of
  ``A^T + A`` and no pivoting, ``SymmetricMode``, as befits the SPD ``K_ii``), refactored
  whenever ``lam`` or ``mu`` change (the paper's joint proposal changes them at every step),
  reused otherwise;
* ``E_r = u^T K u / 2`` from the sparse stiffness matrix;
* ``E_s`` by the 4-point Gauss rule on every tetrahedron, the moving image sampled with
  :func:`scipy.ndimage.map_coordinates` (order 1, ``mode="grid-constant"``: a point within
  one voxel outside the grid blends toward ``cval``, as :func:`bayesreg.data.images.interpolate`),
  its values rounded to ``model.moving_dtype`` as the posterior stores them;
* scaled Beta priors and the hard constraints of :mod:`bayesreg.model.posterior` (parameter
  outside its support, a node where the skull's smooth signed distance is ``>= 0``, an
  inverted element) give ``-inf``.  The signed distance is rebuilt here from the label map
  with SciPy (:func:`scipy.ndimage.distance_transform_edt` between voxel centres, shifted
  half a voxel, the grid padded by forbidden voxels, pockets not connected to the mesh at
  rest forbidden, read by :func:`scipy.ndimage.map_coordinates` at order 3 without
  prefilter: the cubic B-spline quasi-interpolant of :mod:`bayesreg.mesh.constraints`).

Nothing here calls JAX: only the problem's host arrays (mesh, images, priors) are read.
"""

from __future__ import annotations

import time

import numpy as np
import scipy.ndimage as ndi
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from scipy.special import betaln

from bayesreg.data import labels as L
from bayesreg.fem.element import element_stiffness

__all__ = ["GAUSS_BARY", "ReferencePosterior", "reference_mh"]

_A = (5.0 + 3.0 * np.sqrt(5.0)) / 20.0
_B = (5.0 - np.sqrt(5.0)) / 20.0
GAUSS_BARY = np.full((4, 4), _B) + np.eye(4) * (_A - _B)
"""Barycentric coordinates ``(4 points, 4 nodes)`` of the degree-2 4-point rule."""


def _world_to_voxel(affine, points):
    inv = np.linalg.inv(np.asarray(affine, dtype=np.float64))
    return points @ inv[:3, :3].T + inv[:3, 3]


def _signed_distance(skull, affine, nodes, pad=5):
    """Samples of the skull's signed distance (mm, > 0 forbidden) on the label grid padded by
    ``pad`` forbidden voxels, and the padded grid's affine: allowed voxels not 6-connected to
    a node at rest are forbidden; the Euclidean distance between voxel centres of the two
    classes less half a voxel, so that 0 lies on the faces between them."""
    comp, _ = ndi.label(~skull)
    idx = np.floor(_world_to_voxel(affine, nodes) + 0.5).astype(np.int64)
    ok = np.all((idx >= 0) & (idx < np.array(skull.shape)), axis=1)
    seeds = np.unique(comp[tuple(idx[ok].T)])
    forbidden = np.pad(~np.isin(comp, seeds[seeds > 0]), pad, constant_values=True)
    spacing = np.linalg.norm(affine[:3, :3], axis=0)
    half = 0.5 * spacing.min()
    sd = np.where(forbidden, ndi.distance_transform_edt(forbidden, sampling=spacing) - half,
                  half - ndi.distance_transform_edt(~forbidden, sampling=spacing))
    shift = np.eye(4)
    shift[:3, 3] = -pad
    return sd, affine @ shift


class ReferencePosterior:
    """``theta -> log p`` in NumPy/SciPy for a :class:`bayesreg.model.problem.Problem`.

    Parameters
    ----------
    problem : bayesreg.model.problem.Problem
    cfg : bayesreg.config.Config
        Temperatures, priors and image smoothing are read from it (as
        :func:`bayesreg.model.problem.assemble` does).
    permc_spec : str
        Column ordering of :func:`scipy.sparse.linalg.splu` (``MMD_AT_PLUS_A``: 0.02 / 0.3 /
        6 s per factor at 900 / 3400 / 9800 nodes on a 2-core CPU; ``COLAMD`` about 2x slower).

    Attributes
    ----------
    n_factor, factor_s, n_solve, solve_s, ssd_s : counters of the work done (for the time split)
    """

    def __init__(self, problem, cfg, *, permc_spec: str = "MMD_AT_PLUS_A"):
        mesh, post = problem.mesh, problem.posterior
        self.permc_spec = permc_spec
        self.nodes = np.asarray(mesh.nodes, dtype=np.float64)
        self.tets = np.asarray(mesh.tets, dtype=np.int64)
        n = len(self.nodes)
        self.boundary = np.asarray(mesh.boundary, dtype=np.int64)
        is_b = np.zeros(n, bool)
        is_b[self.boundary] = True
        self.interior = np.flatnonzero(~is_b)
        self.nb3 = 3 * len(self.boundary)

        # parameters: groups, fixed values, priors (host copies of the posterior's arrays)
        self.group = np.asarray(problem.element_group, dtype=np.int64)
        self.base = np.asarray(post.base, dtype=np.float64)
        self.free_index = np.asarray(post.free_index, dtype=np.int64)
        self.n_groups = len(self.base) // 2
        self.prior = tuple(np.asarray(a, dtype=np.float64) for a in
                           (post.prior.a, post.prior.b, post.prior.r1, post.prior.r2))
        self.inv_t_s = 1.0 / cfg.model.t_s
        self.inv_t_r = 1.0 / cfg.model.t_r

        # stiffness: one common pattern, unit data per (lam|mu, group)
        klam = element_stiffness(self.nodes, self.tets, 1.0, 0.0)  # (M, 12, 12)
        kmu = element_stiffness(self.nodes, self.tets, 0.0, 1.0)
        dof = (3 * self.tets[:, :, None] + np.arange(3)).reshape(len(self.tets), 12)
        rows = np.repeat(dof, 12, axis=1).ravel()
        cols = np.tile(dof, (1, 12)).ravel()
        keys, inverse = np.unique(rows * (3 * n) + cols, return_inverse=True)
        nnz = len(keys)
        elem = np.repeat(self.group, 144)
        self.unit = np.zeros((2 * self.n_groups, nnz))
        for k, ke in enumerate((klam, kmu)):
            vals = ke.ravel()
            for g in range(self.n_groups):
                self.unit[k * self.n_groups + g] = np.bincount(
                    inverse, weights=np.where(elem == g, vals, 0.0), minlength=nnz)
        self.rows, self.cols = keys // (3 * n), keys % (3 * n)

        # K_ii (CSC, for splu) and K_ib (CSR) as selections of the common data array
        dof_pos = np.full(3 * n, -1, np.int64)
        b_dof = (3 * self.boundary[:, None] + np.arange(3)).ravel()
        i_dof = (3 * self.interior[:, None] + np.arange(3)).ravel()
        dof_pos[b_dof] = np.arange(len(b_dof))
        dof_pos[i_dof] = np.arange(len(i_dof))
        row_i, col_i = ~is_b[self.rows // 3], ~is_b[self.cols // 3]
        self.n_i3 = len(i_dof)

        sel = np.flatnonzero(row_i & col_i)
        r, c = dof_pos[self.rows[sel]], dof_pos[self.cols[sel]]
        order = np.lexsort((r, c))  # column-major for CSC
        self.ii_sel, self.ii_indices = sel[order], r[order]
        self.ii_indptr = np.concatenate([[0], np.cumsum(np.bincount(c, minlength=self.n_i3))])

        sel = np.flatnonzero(row_i & ~col_i)
        r, c = dof_pos[self.rows[sel]], dof_pos[self.cols[sel]]
        order = np.lexsort((c, r))  # row-major for CSR
        self.ib_sel, self.ib_indices = sel[order], c[order]
        self.ib_indptr = np.concatenate([[0], np.cumsum(np.bincount(r, minlength=self.n_i3))])

        # similarity: Gauss points, weights, f at the Gauss points, m and its world-to-voxel map
        x = self.nodes[self.tets]
        self.points = np.einsum("qa,mad->mqd", GAUSS_BARY, x)
        det = np.linalg.det(np.stack([x[:, 1] - x[:, 0], x[:, 2] - x[:, 0], x[:, 3] - x[:, 0]], -1))
        self.weights = np.repeat(np.abs(det)[:, None] / 24.0, 4, axis=1)  # V_e / 4
        f, m = problem.f, problem.m
        if cfg.data.smoothing_mm > 0:
            f, m = (type(i)(ndi.gaussian_filter(i.data, cfg.data.smoothing_mm / i.spacing), i.affine)
                    for i in (f, m))
        self.cval = float(np.asarray(post.similarity.cval))
        self.f_q = self._sample(np.asarray(f.data, np.float64), f.affine, self.points)
        # stored as the posterior stores it (model.moving_dtype: its values rounded once)
        self.m = np.asarray(m.data, np.float64).astype(cfg.model.moving_dtype).astype(np.float64)
        self.m_affine = np.asarray(m.affine, np.float64)

        # hard constraint: the skull's smooth signed distance d >= 0 (bayesreg.mesh.constraints)
        self.sd, self.sd_affine = _signed_distance(np.asarray(problem.labels.data) == L.SKULL,
                                                   np.asarray(problem.labels.affine, np.float64),
                                                   self.nodes)

        self._coef = None
        self._lu = None
        self.n_factor = self.n_solve = 0
        self.factor_s = self.solve_s = self.ssd_s = 0.0

    # ---- pieces --------------------------------------------------------------------------

    def skull_distance(self, points):
        """The skull's signed distance (mm, > 0 forbidden) at world points ``(P, 3)``."""
        c = _world_to_voxel(self.sd_affine, points).reshape(-1, 3)
        c = np.clip(c, 0.0, np.array(self.sd.shape) - 1.0).T
        return ndi.map_coordinates(self.sd, c, order=3, prefilter=False, mode="nearest")

    def _sample(self, volume, affine, points):
        c = _world_to_voxel(affine, points).reshape(-1, 3).T
        vals = ndi.map_coordinates(volume, c, order=1, mode="grid-constant", cval=self.cval)
        return vals.reshape(points.shape[:-1])

    def parameters(self, phi):
        """``(lam_g, mu_g)`` per group with the fixed values in place."""
        full = self.base.copy()
        full[self.free_index] = phi
        return full[: self.n_groups], full[self.n_groups:]

    def log_prior(self, phi):
        """``(log p(phi), inside the support)`` of the scaled Beta priors."""
        a, b, r1, r2 = self.prior
        x = (phi - r1) / (r2 - r1)
        inside = bool(np.all((x > 0) & (x < 1) & (phi > 0)))
        xs = np.clip(x, 1e-12, 1 - 1e-12)
        lp = (a - 1) * np.log(xs) + (b - 1) * np.log1p(-xs) - betaln(a, b) - np.log(r2 - r1)
        return float(np.sum(lp)), inside

    def interior_solve(self, coef, data, u_b):
        """``u_i`` ``(n_i, 3)`` from ``K_ii u_i = -K_ib u_b``.

        ``coef`` (the ``[lam_g, mu_g]`` that made ``data``) decides whether ``K_ii`` must be
        refactored: the factor of the previous call is reused while they are unchanged.
        """
        t = time.perf_counter()
        if self._lu is None or not np.array_equal(coef, self._coef):
            k_ii = sp.csc_matrix((data[self.ii_sel], self.ii_indices, self.ii_indptr),
                                 shape=(self.n_i3, self.n_i3))
            # K_ii is SPD: symmetric ordering, no pivoting (default SuperLU pivoting fills in
            # badly: 92 s instead of 6 s for the factor of a 10k-node mesh)
            self._lu = spla.splu(k_ii, permc_spec=self.permc_spec, diag_pivot_thresh=0.0,
                                 options={"SymmetricMode": True})
            self._coef = np.array(coef)
            self.n_factor += 1
            t1 = time.perf_counter()
            self.factor_s += t1 - t
            t = t1
        k_ib = sp.csr_matrix((data[self.ib_sel], self.ib_indices, self.ib_indptr),
                             shape=(self.n_i3, self.nb3))
        u_i = self._lu.solve(-(k_ib @ u_b.ravel()))
        self.n_solve += 1
        self.solve_s += time.perf_counter() - t
        return u_i.reshape(-1, 3)

    def e_s(self, u):
        """SSD (paper Eq. 1) for nodal displacements ``u`` ``(N, 3)``."""
        t = time.perf_counter()
        u_q = np.einsum("qa,mad->mqd", GAUSS_BARY, u[self.tets])
        m_q = self._sample(self.m, self.m_affine, self.points + u_q)
        out = float(np.sum(self.weights * (self.f_q - m_q) ** 2))
        self.ssd_s += time.perf_counter() - t
        return out

    # ---- the log-density -----------------------------------------------------------------

    def __call__(self, theta) -> float:
        """Unnormalised log posterior at ``theta = [u_b.ravel(), phi]`` (``-inf`` if invalid)."""
        theta = np.asarray(theta, dtype=np.float64)
        u_b, phi = theta[: self.nb3].reshape(-1, 3), theta[self.nb3:]
        log_prior, inside = self.log_prior(phi)
        if not inside:
            return -np.inf
        lam_g, mu_g = self.parameters(phi)
        coef = np.concatenate([lam_g, mu_g])
        data = coef @ self.unit
        u = np.zeros_like(self.nodes)
        u[self.boundary] = u_b
        u[self.interior] = self.interior_solve(coef, data, u_b)
        uf = u.ravel()
        e_r = 0.5 * float(np.dot(data, uf[self.rows] * uf[self.cols]))
        e_s = self.e_s(u)
        x = (self.nodes + u)[self.tets]
        det = np.einsum("mi,mi->m", np.cross(x[:, 1] - x[:, 0], x[:, 2] - x[:, 0]), x[:, 3] - x[:, 0])
        if np.any(det <= 0) or np.any(self.skull_distance(self.nodes + u) >= 0.0):
            return -np.inf
        if not (np.isfinite(e_s) and np.isfinite(e_r)):
            return -np.inf
        return -e_s * self.inv_t_s - e_r * self.inv_t_r + log_prior

    def reset_counters(self):
        self.n_factor = self.n_solve = 0
        self.factor_s = self.solve_s = self.ssd_s = 0.0


def reference_mh(ref: ReferencePosterior, theta0, sigma, n_steps: int, *, seed: int = 0,
                 max_seconds: float | None = None) -> dict:
    """Random-walk MH with the paper's joint isotropic proposal (Eq. 14), one chain.

    ``theta* = theta + sigma * z`` (``sigma`` ``(dim,)``), accepted with probability
    ``min(1, p(theta*) / p(theta))`` (Eq. 13).  Stops after ``n_steps`` or ``max_seconds``.

    Returns
    -------
    dict with ``steps``, ``seconds``, ``steps_per_s``, ``acceptance`` and the time split
    (``factor_s``, ``solve_s``, ``ssd_s``, ``proposal_s`` in seconds per step).
    """
    rng = np.random.default_rng(seed)
    theta = np.array(theta0, dtype=np.float64)
    sigma = np.asarray(sigma, dtype=np.float64)
    lp = ref(theta)
    if not np.isfinite(lp):
        raise ValueError("the reference chain starts at zero posterior density")
    ref.reset_counters()
    accepted = 0
    prop_s = 0.0
    t0 = time.perf_counter()
    k = 0
    while k < n_steps:
        t = time.perf_counter()
        proposal = theta + sigma * rng.standard_normal(theta.shape)
        prop_s += time.perf_counter() - t
        lp_new = ref(proposal)
        if np.log(rng.uniform()) < lp_new - lp:
            theta, lp = proposal, lp_new
            accepted += 1
        k += 1
        if max_seconds is not None and time.perf_counter() - t0 > max_seconds:
            break
    seconds = time.perf_counter() - t0
    return {
        "steps": k, "seconds": seconds, "steps_per_s": k / seconds, "acceptance": accepted / k,
        "factorisations": ref.n_factor,
        "factor_ms_per_step": 1e3 * ref.factor_s / k,
        "solve_ms_per_step": 1e3 * ref.solve_s / k,
        "ssd_ms_per_step": 1e3 * ref.ssd_s / k,
        "proposal_ms_per_step": 1e3 * prop_s / k,
    }

"""The main job: images -> labels -> mesh -> FE operators -> posterior -> sampler -> outputs.

:func:`prepare` builds a :class:`Problem` (data, mesh, synthetic truth, log-density);
:func:`sample_problem` runs the chains; :func:`run` does both and writes the run directory
(:mod:`bayesreg.outputs`).  From a notebook::

    import bayesreg
    result = bayesreg.run("configs/quickstart.yaml", out="runs/qs")
    result.posterior  # ArviZ DataTree
"""

from __future__ import annotations

import hashlib
import time
import warnings
from functools import partial
from types import SimpleNamespace
from typing import NamedTuple

import numpy as np
import scipy.linalg as sla
import scipy.ndimage as ndi
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from bayesreg import _xla

_xla.configure()
import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402

from bayesreg import labels as L  # noqa: E402
from bayesreg.config import Config, load_config  # noqa: E402
from bayesreg.fem import stiffness_matrix  # noqa: E402
from bayesreg.images import (  # noqa: E402
    Image, _count_nonfinite, check_same_frame, interpolate_numpy, load_nifti, mni152, pad,
    resample_to_spacing, to_reference_grid,
)
from bayesreg.mesh import (  # noqa: E402
    Mesh, carve_skull, mesh_brain, mesh_brain_sized, read_mesh, signed_volumes)
from bayesreg.posterior import (  # noqa: E402
    ParamLayout, Posterior, build_posterior, elastic_groups, log_density, log_density_condensed,
    add_normaliser, log_normaliser, split_position, with_skull_barrier,
)
from bayesreg.posterior import condensation as condensation_map  # noqa: E402
from bayesreg.posterior import preconditioner as preconditioner_at  # noqa: E402
from bayesreg.kernels import make_target  # noqa: E402
from bayesreg.sampler import (  # noqa: E402
    Condensation, Preconditioner, SamplerResult, sample, sample_gradient,
)
from bayesreg.solver import DENSE_MAX_DOFS  # noqa: E402
from bayesreg.similarity import build_ssd, sample_moving  # noqa: E402
from bayesreg.synthetic import Truth, brain_shift, constrained_shift, warp_image  # noqa: E402

__all__ = [
    "Problem", "make_data", "assemble", "prepare", "save_problem", "load_problem", "start_center",
    "start_check",
    "find_mode", "laplace_precision", "initial_positions", "proposal_scale", "Initialisation",
    "initialise", "dense_budget_bytes", "dense_preconditioning", "cg_preconditioner",
    "sample_problem", "run",
]


class Problem(NamedTuple):
    """Everything needed to sample and to report one registration problem.

    Attributes
    ----------
    f, m : Image  pre-/intra-operative images, intensities scaled (see :func:`prepare`)
    labels : Image  internal label coding
    mesh : Mesh
    layout : ParamLayout
    element_group : (M,) int
    posterior : Posterior
    truth : Truth or None  (synthetic cases)
    phi_true : (n_free,) or None  true free parameters, where defined
    phi_init : (n_free,)  central start of the elastic parameters
    intensity_scale : float  f and m were divided by it
    n_skull_carved : int  skull voxels freed next to the mesh (:func:`bayesreg.mesh.carve_skull`)
    timings : dict
    truth_info : dict or None  how the truth was made (constrained minimiser figures)
    mesh_info : dict or None  how the mesh was made: its edge length (mm) and, with
        ``mesh.target_nodes``, the attempts of :func:`bayesreg.mesh.mesh_brain_sized`
    """

    f: Image
    m: Image
    labels: Image
    mesh: Mesh
    layout: ParamLayout
    element_group: np.ndarray
    posterior: Posterior
    truth: Truth | None
    phi_true: np.ndarray | None
    phi_init: np.ndarray
    intensity_scale: float
    n_skull_carved: int
    timings: dict
    truth_info: dict | None = None
    mesh_info: dict | None = None


def _load_data(cfg: Config):
    d = cfg.data
    if d.source == "mni152":
        t1, gm, wm, mask = mni152(d.resolution_mm or 1.0, margin_mm=4 * d.skull_margin_mm)
        labels = L.labels_from_probabilities(gm, wm, mask, skull_margin_mm=d.skull_margin_mm)
        return t1, None, labels
    from bayesreg.labels import remap_labels

    f = load_nifti(d.fixed)
    lab = load_nifti(d.labels)
    m = load_nifti(d.moving) if d.moving is not None else None
    for key, img in (("data.fixed", f), ("data.labels", lab), ("data.moving", m)):
        bad = 0 if img is None else _count_nonfinite(img.data)
        if bad:
            raise ValueError(f"{key} ({getattr(d, key[5:])}) has {bad} non-finite voxels (NaN or "
                             "inf): replace them (e.g. by 0 outside the head) before registering")
    # the images may lie on different grids of one world frame: resampled onto f's grid
    check_same_frame(d.fixed, d.labels, d.moving, names=("data.fixed", "data.labels", "data.moving"))
    lab = to_reference_grid(lab, f, name="data.labels", reference_name="data.fixed", order=0)
    if m is not None:
        m = to_reference_grid(m, f, name="data.moving", reference_name="data.fixed", order=1)
    if d.resolution_mm is not None:
        f = resample_to_spacing(f, d.resolution_mm, order=1)
        lab = resample_to_spacing(lab, d.resolution_mm, order=0)
        m = resample_to_spacing(m, d.resolution_mm, order=1) if m is not None else None
    margin = 4 * d.skull_margin_mm
    labels = remap_labels(pad(lab, margin), d.label_coding)
    f = pad(f, margin)
    m = pad(m, margin) if m is not None else None
    return f, m, labels


def _layout(cfg: Config, mesh: Mesh):
    mode = cfg.model.elastic
    if mode == "uniform":
        names, group = ("all",), np.zeros(len(mesh.tets), np.int64)
    elif mode == "tissue":
        names, group = L.TISSUES, mesh.tissue.astype(np.int64)
    else:
        names = tuple(f"e{k}" for k in range(len(mesh.tets)))
        group = np.arange(len(mesh.tets))
    fixed = ()
    fx = cfg.model.fixed
    if fx is not None:
        if fx.group not in names:
            raise ValueError(f"model.fixed.group '{fx.group}' is not one of the groups {names[:5]}...")
        fixed = ((fx.param, names.index(fx.group), fx.value),)
    free = tuple(
        (p, g) for p in ("lam", "mu") for g in range(len(names))
        if not any(p == fp and g == fg for fp, fg, _ in fixed)
    )
    return ParamLayout(tuple(names), free, fixed), group


def _group_values(layout: ParamLayout, tv, group, mesh: Mesh):
    """Per-group value from per-tissue values (uniform: volume-weighted tissue mean)."""
    tissue_vals = np.array([tv.csf, tv.gm, tv.wm])
    names = layout.group_names
    if names == L.TISSUES:
        return tissue_vals
    if names == ("all",):
        vol = signed_volumes(mesh.nodes, mesh.tets)
        return np.array([np.sum(vol * tissue_vals[mesh.tissue]) / vol.sum()])
    return tissue_vals[mesh.tissue]


def _make_truth(cfg: Config, mesh: Mesh, labels: Image):
    """Synthetic truth per ``cfg.synthetic``; returns ``(Truth, info dict)``.

    Raises
    ------
    ValueError
        If the constrained minimiser does not converge, or the truth puts a node in the
        skull region or inverts an element (nothing is hidden: the figures are in the message).
    """
    s = cfg.synthetic
    lam_t = np.array([s.lam.csf, s.lam.gm, s.lam.wm])[mesh.tissue]
    mu_t = np.array([s.mu.csf, s.mu.gm, s.mu.wm])[mesh.tissue]
    pushed = None if s.pushed_nodes is None else np.asarray(s.pushed_nodes, np.int64)
    if s.truth == "constrained":
        forbidden = Image((labels.data == L.SKULL).astype(np.uint8), labels.affine)
        truth, info = constrained_shift(
            mesh, lam_t, mu_t, forbidden, shift_mm=s.shift_mm, n_pushed=s.n_pushed, pushed=pushed,
            clearance_mm=s.clearance_mm, tol_mm=s.tol_mm,
        )
        if not info["converged"] or info["n_forbidden_nodes"] or info["n_inverted"]:
            raise ValueError(
                "the constrained ground truth failed: converged {converged}, max violation "
                "{max_violation_mm:.3g} mm (tol {tol_mm}), nodes in the skull {n_forbidden_nodes}, "
                "inverted elements {n_inverted}".format(**info)
            )
    else:
        if pushed is not None:
            raise ValueError("synthetic.pushed_nodes needs synthetic.truth: constrained")
        truth = brain_shift(mesh, lam_t, mu_t, shift_mm=s.shift_mm, n_pushed=s.n_pushed,
                            falloff_mm=s.falloff_mm)
        info = {"truth": "smooth", "shift_mm": s.shift_mm, "pushed": truth.pushed.tolist()}
        # the constrained minimiser checks both itself; the smooth push is not constrained
        moved = interpolate_numpy(labels, mesh.nodes + truth.u, order=0, cval=L.SKULL)
        if np.any(moved == L.SKULL):
            raise ValueError(
                f"the synthetic truth moves {int(np.sum(moved == L.SKULL))} node(s) into the "
                "skull region; lower synthetic.shift_mm or widen data.skull_margin_mm"
            )
        info["n_inverted"] = int(np.sum(signed_volumes(mesh.nodes + truth.u, mesh.tets) <= 0))
    info["lam"] = s.lam.model_dump()
    info["mu"] = s.mu.model_dump()
    return truth, info


def _sha256(path) -> str:
    """Hex SHA-256 of a file's bytes (recorded with a run's ``mesh.file``)."""
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def make_data(cfg: Config) -> dict:
    """The expensive, non-reproducible part of :func:`prepare`: images, labels, mesh, truth.

    Intensities of ``f`` and ``m`` are divided by the ``data.intensity_percentile``-th
    percentile of ``f`` inside the intracranial volume (about [0, 1] afterwards), so that
    ``E_s`` and ``T_s`` have image-independent units (``intensity^2 mm^3``).  With a
    synthetic case, ``m`` is ``f`` warped exactly through the FE map of the truth.

    Returns
    -------
    dict with ``f, m, labels`` (Image), ``mesh``, ``truth`` (Truth or None),
    ``truth_info`` (dict or None), ``intensity_scale``, ``n_skull_carved``, ``timings``,
    ``mesh_info`` (dict: the edge length and, with ``mesh.target_nodes``, the attempts; with
    ``mesh.file``, the file and its SHA-256).

    Raises
    ------
    FileNotFoundError
        A data file or ``mesh.file`` does not exist.
    MeshError
        Meshing fails, or ``mesh.file`` is unusable (:func:`bayesreg.mesh.read_mesh`).

    Warns
    -----
    UserWarning
        Nodes of ``mesh.file`` lie in the skull region of the label map at rest: the skull
        voxels under and near the mesh become background (:func:`bayesreg.mesh.carve_skull`,
        as for a generated mesh that pokes past the brain mask), which a given mesh should
        not need.
    """
    timings = {}
    t = time.perf_counter()
    f, m, labels = _load_data(cfg)
    inside = np.isin(labels.data, L.TISSUE_LABELS)
    scale = float(np.percentile(np.asarray(f.data)[inside], cfg.data.intensity_percentile))
    if not scale > 0:
        raise ValueError("the fixed image is zero inside the intracranial volume")
    f = Image(np.asarray(f.data, np.float64) / scale, f.affine)
    if m is not None:
        m = Image(np.asarray(m.data, np.float64) / scale, m.affine)
    timings["data_s"] = time.perf_counter() - t

    t = time.perf_counter()
    mc = cfg.mesh
    mesh_kw = {"smoothing_sigma_mm": mc.smoothing_sigma_mm, "epsilon": mc.epsilon}
    if mc.file is not None:
        mesh = read_mesh(mc.file, labels)
        mesh_info = {"file": str(mc.file), "sha256": _sha256(mc.file)}
    elif mc.target_nodes is None:
        mesh = mesh_brain(labels, edge_length_mm=mc.edge_length_mm, **mesh_kw)
        mesh_info = {"edge_length_mm": mc.edge_length_mm}
    else:
        mesh, mesh_info = mesh_brain_sized(
            labels, mc.target_nodes, tolerance=mc.target_tolerance, max_attempts=mc.max_attempts,
            edge_length_mm=mc.edge_length_mm, **mesh_kw)
    if mc.file is not None:
        in_skull = int(np.sum(interpolate_numpy(labels, mesh.nodes, order=0, cval=L.SKULL) == L.SKULL))
    labels, n_carved = carve_skull(labels, mesh)
    if mc.file is not None and in_skull:
        warnings.warn(
            f"mesh.file {mc.file}: {in_skull} of its {len(mesh.nodes)} nodes lie in the skull "
            f"region of the label map at rest (or outside its grid); the {n_carved} skull voxels "
            "under and near the mesh became background, so the skull constraint only holds "
            "beyond them.  Is the mesh of these images?", UserWarning, stacklevel=2)
    timings["mesh_s"] = time.perf_counter() - t
    empty = [n for n, c in zip(L.TISSUES, np.bincount(mesh.tissue, minlength=3)) if c == 0]
    if cfg.model.elastic == "tissue" and empty:
        raise ValueError(f"no mesh element is labelled {empty}: refine the mesh or use elastic: uniform")

    truth = truth_info = None
    t = time.perf_counter()
    if cfg.synthetic.enabled:
        truth, truth_info = _make_truth(cfg, mesh, labels)
        m = warp_image(f, mesh, truth.u, background=0.0, outside=cfg.synthetic.outside)
    elif m is None:  # pragma: no cover - guarded by the config validator
        raise ValueError("no intra-operative image")
    timings["synthetic_s"] = time.perf_counter() - t
    return {"f": f, "m": m, "labels": labels, "mesh": mesh, "truth": truth,
            "truth_info": truth_info, "intensity_scale": scale, "n_skull_carved": n_carved,
            "timings": timings, "mesh_info": mesh_info}


def assemble(cfg: Config, data: dict) -> Problem:
    """Build the parameter layout, priors and posterior of :func:`make_data`'s output.

    With ``data.smoothing_mm > 0`` the posterior's copies of ``f`` and ``m`` are smoothed
    by a Gaussian of that sigma (``m`` was made from the unsmoothed ``f``).
    """
    f, m, labels, mesh, truth = (data[k] for k in ("f", "m", "labels", "mesh", "truth"))
    layout, group = _layout(cfg, mesh)

    def free_values(lam_tv, mu_tv):
        lam_g = _group_values(layout, lam_tv, group, mesh)
        mu_g = _group_values(layout, mu_tv, group, mesh)
        return np.array([(lam_g if p == "lam" else mu_g)[g] for p, g in layout.free])

    phi_init = free_values(cfg.model.initial_lam, cfg.model.initial_mu)
    phi_true = None
    if truth is not None and layout.group_names != ("all",):
        phi_true = free_values(cfg.synthetic.lam, cfg.synthetic.mu)

    def prior_tuple(pr):
        if hasattr(pr, "csf"):
            return [prior_tuple(getattr(pr, t)) for t in L.TISSUES]
        return (pr.a, pr.b, pr.r1, pr.r2)

    prior = {"lam": prior_tuple(cfg.model.prior_lam), "mu": prior_tuple(cfg.model.prior_mu)}
    f_s, m_s = f, m
    if cfg.data.smoothing_mm > 0:
        f_s, m_s = (Image(ndi.gaussian_filter(i.data, cfg.data.smoothing_mm / i.spacing), i.affine)
                    for i in (f, m))
    forbidden = Image((labels.data == L.SKULL).astype(np.uint8), labels.affine)
    # m kept over the box that nodes outside the skull can reach (the same values of E_s)
    reach = Image((labels.data != L.SKULL).astype(np.uint8), labels.affine)
    choice = cfg.solver.preconditioner  # spectral is validated to have one group (config)
    post = build_posterior(
        mesh, build_ssd(mesh.nodes, mesh.tets, f_s, m_s, quadrature_level=cfg.model.quadrature_level,
                        reach=reach, moving_dtype=cfg.model.moving_dtype),
        forbidden,
        t_s=cfg.model.t_s, t_r=cfg.model.t_r, layout=layout, element_group=group,
        prior=prior, phi_ref=phi_init, barrier_mm=cfg.model.skull_barrier_mm,
        spectral=choice in ("auto", "spectral"),
    )
    return Problem(f, m, labels, mesh, layout, group, post, truth, phi_true, phi_init,
                   data["intensity_scale"], data["n_skull_carved"], dict(data["timings"]),
                   data.get("truth_info"), data.get("mesh_info"))


def prepare(cfg: Config) -> Problem:
    """Load data, derive labels, mesh, make the synthetic truth (if enabled), build the posterior
    (:func:`make_data` then :func:`assemble`)."""
    return assemble(cfg, make_data(cfg))


def save_problem(problem: Problem, path) -> None:
    """Write the data of a problem (images, mesh, truth) to one compressed ``.npz``, atomically.

    :func:`load_problem` rebuilds the same :class:`Problem` without meshing again (meshing
    with fTetWild is not bit-reproducible, so a resumed run must reuse the mesh).
    """
    import json
    from pathlib import Path

    from bayesreg.checkpoint import savez_atomic

    path = Path(path)
    arrays = {
        "f": problem.f.data, "f_affine": problem.f.affine,
        "m": np.asarray(problem.m.data), "m_affine": problem.m.affine,
        "labels": problem.labels.data, "labels_affine": problem.labels.affine,
        "nodes": problem.mesh.nodes, "tets": problem.mesh.tets, "tissue": problem.mesh.tissue,
        "boundary": problem.mesh.boundary,
        "meta": np.array(json.dumps({
            "intensity_scale": problem.intensity_scale, "n_skull_carved": problem.n_skull_carved,
            "timings": problem.timings, "truth_info": problem.truth_info,
            "mesh_info": problem.mesh_info,
        })),
    }
    if problem.truth is not None:
        t = problem.truth
        arrays.update(truth_u=t.u, truth_lam_e=t.lam_e, truth_mu_e=t.mu_e, truth_pushed=t.pushed)
    savez_atomic(path, compressed=True, **arrays)


def load_problem(path, cfg: Config) -> Problem:
    """Inverse of :func:`save_problem` (the posterior is rebuilt from ``cfg``).

    Raises
    ------
    ValueError
        If the file is damaged or incomplete (not a readable ``.npz`` of a problem).
    """
    import json
    import zipfile

    try:
        z = np.load(path, allow_pickle=False)
        meta = json.loads(str(z["meta"]))
        truth = None
        if "truth_u" in z:
            truth = Truth(z["truth_u"], z["truth_lam_e"], z["truth_mu_e"], z["truth_pushed"])
        data = {
            "f": Image(z["f"], z["f_affine"]), "m": Image(z["m"], z["m_affine"]),
            "labels": Image(z["labels"], z["labels_affine"]),
            "mesh": Mesh(z["nodes"], z["tets"], z["tissue"], z["boundary"]),
            "truth": truth, "truth_info": meta["truth_info"],
            "intensity_scale": meta["intensity_scale"], "n_skull_carved": meta["n_skull_carved"],
            "timings": meta["timings"], "mesh_info": meta.get("mesh_info"),  # (older: none)
        }
    except (zipfile.BadZipFile, EOFError, KeyError, json.JSONDecodeError) as exc:
        raise ValueError(f"{path} is damaged or incomplete ({type(exc).__name__}: {exc}): "
                         "the problem cannot be read back") from exc
    return assemble(cfg, data)


def make_logdensity(problem: Problem, cfg: Config, *, preconditioned: bool = False):
    """``(theta, interior_guess) -> (logp, aux)`` closed over the problem (for the sampler).

    With ``model.prior_normaliser: exact`` the normaliser ``(1/2) log pdet S(lam, mu)``
    (:func:`bayesreg.posterior.log_normaliser`, one dense factorisation) is added.
    ``preconditioned``: ``(theta, interior_guess, precond) -> (logp, aux)`` instead, the
    interior solve preconditioned by ``precond`` (:func:`bayesreg.posterior.preconditioner`).
    """
    post = problem.posterior
    base = partial(log_density, post, rtol=cfg.solver.rtol, maxiter=cfg.solver.maxiter)

    def logdensity(theta, interior, precond=None):
        lp, aux = base(theta, interior, precond=precond)
        if cfg.model.prior_normaliser == "paper":
            return lp, aux
        ln = log_normaliser(post, split_position(post, theta)[1])
        return add_normaliser(lp, ln), aux

    if preconditioned:
        return logdensity
    return lambda theta, interior: logdensity(theta, interior)


DENSE_HOST_BUDGET = 2 * 2**30  # bytes of the chains' float32 K_ii^-1 together, on a CPU


def dense_budget_bytes() -> int:
    """Bytes that the chains' dense preconditioners (float32 ``K_ii^-1``) may take together.

    On a CPU :data:`DENSE_HOST_BUDGET` (2 GiB).  On an accelerator that reports its memory
    (``memory_stats()['bytes_limit']`` of the default device), a sixteenth of it and at
    least 2 GiB: building the inverses peaks at about 4 times their float32 size (float64
    ``K_ii`` and its factor; measured on an H200, 2026-11-26: 36.0 GB at 1,024 chains of
    8.75 MB inverses), so the build stays within a quarter of the device.  On that H200
    (a 112.6 GB limit: 7.0 GB, 800 chains at the paper's size) the dense preconditioner
    ran 2.0-7.2x the MH steps/s of block Jacobi from 1 to 256 chains and 0.98x at 1,024,
    where both run about 30,000 steps/s in total (``benchmarks/README.md``, GPU).
    """
    if jax.default_backend() == "cpu":
        return DENSE_HOST_BUDGET
    try:
        limit = int((jax.devices()[0].memory_stats() or {})["bytes_limit"])
    except (KeyError, TypeError, ValueError, RuntimeError, NotImplementedError):
        return DENSE_HOST_BUDGET  # a backend that does not report its memory
    return max(DENSE_HOST_BUDGET, limit // 16)


def dense_preconditioning(problem: Problem, cfg: Config, *, n_chains: int | None = None) -> bool:
    """Whether the samplers' CG solves use the dense preconditioner (``solver.preconditioner``).

    ``auto``: not where the posterior has the spectral one (one parameter group, see
    :func:`cg_preconditioner`); else where ``3 n_i <= DENSE_MAX_DOFS`` (4096) and the
    chains' float32 inverses, ``4 (3 n_i)^2`` bytes each, fit :func:`dense_budget_bytes`
    together (2 GiB on a CPU; the paper's size: 7.5-8.75 MB a chain; the 3,400-node mesh,
    7,200 interior DOFs, stays with block Jacobi).  ``n_chains`` defaults to
    ``sampler.chains``.
    """
    choice = cfg.solver.preconditioner
    if choice != "auto":
        return choice == "dense"
    if problem.posterior.spectral is not None:
        return False
    n = 3 * problem.posterior.op.n_interior
    chains = cfg.sampler.chains if n_chains is None else n_chains
    return n <= DENSE_MAX_DOFS and chains * 4 * n * n <= dense_budget_bytes()


def cg_preconditioner(problem: Problem, cfg: Config, *, n_chains: int | None = None) -> str:
    """Name of the samplers' CG preconditioner: ``spectral``, ``dense`` or ``block-jacobi``."""
    if dense_preconditioning(problem, cfg, n_chains=n_chains):
        return "dense"
    return "spectral" if problem.posterior.spectral is not None else "block-jacobi"


def _preconditioner_rw(problem: Problem, cfg: Config) -> Preconditioner:
    """The random walk's :class:`~bayesreg.sampler.Preconditioner` (dense ``K_ii^-1``)."""
    post = problem.posterior
    return Preconditioner(make_logdensity(problem, cfg, preconditioned=True),
                          lambda theta: preconditioner_at(post, theta))


def _condensed_rw(problem: Problem, cfg: Config):
    """The random walk's :class:`~bayesreg.sampler.Condensation` (cache ``(H, log_norm)``)."""
    post = problem.posterior
    exact = cfg.model.prior_normaliser == "exact"

    def build(theta):
        ln = log_normaliser(post, split_position(post, theta)[1]) if exact else jnp.zeros(())
        return condensation_map(post, theta), ln

    def logdensity(theta, cache):
        lp, aux = log_density_condensed(post, theta, cache[0])
        return add_normaliser(lp, cache[1]), aux

    return Condensation(logdensity, build, 0, cfg.sampler.u_moves)


def start_center(problem: Problem, cfg: Config, *, check=None) -> tuple[np.ndarray, dict]:
    """Central start ``(dim,)`` of the chains and how it was made.

    ``u_b``: ``init.fraction * truth`` (``init.start: between``, paper Sec. 4.2; identity
    without a truth) or the displacement of a fast registration of ``f`` to ``m``
    (``init.start: registration``: scikit-image optical flow, see
    :func:`bayesreg.registration.optical_flow_displacement`) at the boundary nodes.  Nodes
    that the start would put into the skull (or an element it would invert) are pulled back
    toward zero by halving until the start is valid.  Parameters: ``model.initial_*``.

    Parameters
    ----------
    check : callable, optional
        The jitted start check of :func:`start_check` (built here if not given; pass the
        one :func:`initial_positions` uses so that one program serves both).

    Returns
    -------
    theta : (dim,) ndarray
    info : dict  ``{"start", "shrink"}`` (and the registration time)

    Raises
    ------
    ValueError
        If 30 halvings of the start's displacements find no valid start.
    """
    post, mesh = problem.posterior, problem.mesh
    nb = post.n_boundary
    info: dict = {"start": cfg.init.start}
    base_u = np.zeros((nb, 3))
    if cfg.init.start == "registration":
        from bayesreg.registration import displacement_at, optical_flow_displacement

        t = time.perf_counter()
        brain = np.isin(problem.labels.data, L.TISSUE_LABELS)
        f_reg = problem.f
        if problem.truth is not None:  # a synthetic m holds the brain only: so must f
            f_reg = Image(np.where(brain, problem.f.data, 0.0), problem.f.affine)
        flow = optical_flow_displacement(f_reg, problem.m, method=cfg.init.registration,
                                         mask=ndi.binary_dilation(brain, iterations=3))
        base_u = displacement_at(flow, mesh.nodes[mesh.boundary])
        info["registration_s"] = time.perf_counter() - t
    elif problem.truth is not None:
        base_u = cfg.init.fraction * problem.truth.u[mesh.boundary]
    theta = np.concatenate([base_u.ravel(), problem.phi_init])
    check = start_check(problem, cfg) if check is None else check
    shrink = 1.0
    for _ in range(30):
        # the one start, as each of the chains' rows: the program of the dispersed starts
        if np.isfinite(np.asarray(check(jnp.tile(jnp.asarray(theta), (cfg.sampler.chains, 1))))[0]):
            info["shrink"] = shrink
            return theta, info
        # pull back only the offending nodes (in the skull or out of the image) first
        moved = mesh.nodes[mesh.boundary] + theta[: 3 * nb].reshape(nb, 3)
        bad = interpolate_numpy(problem.labels, moved, order=0, cval=L.SKULL) == L.SKULL
        u = theta[: 3 * nb].reshape(nb, 3)
        u[bad if bad.any() else slice(None)] *= 0.5
        theta[: 3 * nb] = u.ravel()
        shrink *= 0.5
    raise ValueError("could not find a valid central start (skull, inverted element or solve)")


MODE_BARRIER_MM = 1.0
"""Width (mm) of the skull barrier that :func:`find_mode` adds to a model without one."""


def find_mode(problem: Problem, cfg: Config, theta0) -> tuple[np.ndarray, dict]:
    """Maximise the log posterior from ``theta0`` (L-BFGS, JAX gradients through the solve).

    Optimises ``u_b`` and, with ``init.optimize_parameters``, the free elastic parameters
    too; otherwise the parameters stay at ``theta0``'s.  The joint search runs in two
    stages of ``init.optimizer_iterations // 2`` L-BFGS iterations each: ``u_b`` alone at
    ``theta0``'s parameters, then ``u_b`` and the parameters together, these in the
    coordinates ``log(phi - r1)`` (the result kept a relative margin 1e-3 inside the prior
    support).  Both choices avoid a trap measured on the paper's uniform model: far from
    the mode the parameter gradient is meaningless, and the logit coordinates of the
    sampler (:func:`bayesreg.posterior.from_unconstrained`) saturate at the bounds, so a
    first joint step that took ``lam`` to its upper bound 1000 never came back (log p
    -10,476 there, where ``lam`` = 10 with ``u_b`` re-optimised gives -9,376).  A step
    into a hard constraint (``-inf``, also beyond ``r2``) lies outside the line search's
    domain and is shortened; if no feasible step gains, the search stops and says so in
    ``message``.  Without a skull barrier in the model (``model.skull_barrier_mm: 0``) the
    search runs on the posterior plus a 1 mm barrier (:func:`bayesreg.posterior.skull_barrier`):
    on the hard wall alone its line search stalls as soon as the gradient points into the
    skull (measured: 9 iterations, boundary error 2.2 mm, on the paper's constrained truth),
    while the barrier's maximum is strictly feasible and within the barrier of the
    constrained one; the chains sample the model as configured.
    With ``prior_normaliser: exact`` this runs without the normaliser
    (it depends on the parameters only, and its gradient costs about eight dense
    factorisations), then the parameters alone are optimised with it (at most 100 steps).

    Returns
    -------
    theta : (dim,) ndarray
    info : dict  ``{"logp_start", "logp_mode", "iterations", "message",
        "search_barrier_mm"}`` (and ``parameter_iterations_exact``); the log p values are
        those of the searched objective (the barrier included)
    """
    post = problem.posterior
    search_barrier = float(post.barrier_width)
    if search_barrier == 0.0:
        search_barrier = MODE_BARRIER_MM
        post = with_skull_barrier(post, search_barrier)
        problem = problem._replace(posterior=post)
    nb3 = 3 * post.n_boundary
    theta0 = np.asarray(theta0, dtype=np.float64)
    zeros = jnp.zeros((post.op.n_interior, 3))
    # the exact normaliser depends on lam, mu only: u_b (and the parameters) are first
    # optimised without it (its gradient costs about eight dense factorisations), then the
    # parameters alone with it (below)
    logdensity = make_logdensity(problem, cfg.model_copy(
        update={"model": cfg.model.model_copy(update={"prior_normaliser": "paper"})}))
    joint = cfg.init.optimize_parameters
    free = slice(0, post.dim if joint else nb3)

    steps = {}  # one jitted L-BFGS step (and its solver) per objective, shared by its searches

    def maximise(logdensity, theta, sl, maxiter):
        """L-BFGS (optax, zoom line search) over ``theta[sl]``, the rest of ``theta`` held.

        The rest is held by a mask (``stop_gradient`` outside ``sl``): with zero gradient
        components L-BFGS's directions have zero components there, so the search is the one
        over ``theta[sl]`` alone, and the searches of one objective over different slices
        share one compiled step (6-8 s a compilation at the quickstart's size).

        A step into a hard constraint (``log p = -inf``) is outside the domain for the line
        search, which shortens it.  scipy's L-BFGS-B was used before: fed a huge value with
        a zero gradient there, its line search collapsed and it reported convergence after
        5 iterations at log p -866,042 on the paper's uniform model, where a plain gradient
        step still gained 3,000."""
        import optax

        if logdensity not in steps:
            solver = optax.lbfgs()

            @jax.jit
            def step(x, state, mask):
                def neg(y):
                    return -logdensity(jnp.where(mask, y, jax.lax.stop_gradient(y)), zeros)[0]

                v, g = optax.value_and_grad_from_state(neg)(x, state=state)
                upd, state = solver.update(g, state, x, value=v, grad=g, value_fn=neg)
                return optax.apply_updates(x, upd), state, v, g

            steps[logdensity] = step, solver
        step, solver = steps[logdensity]
        mask = np.zeros(len(theta), bool)
        mask[sl] = True
        step = partial(step, mask=jnp.asarray(mask))

        x = jnp.asarray(theta)
        state = solver.init(x)
        # optax's initial state holds weakly typed scalars that its update returns strongly
        # typed (same dtypes): made strong here so that `step` compiles once, not twice
        # (5-6 s a compilation at the quickstart's size, three searches per run)
        state = jax.tree.map(lambda a: jnp.asarray(a, dtype=a.dtype), state)
        best_x, best_f, message, nit = x, np.inf, f"reached {maxiter} iterations", 0
        for nit in range(1, maxiter + 1):
            x_new, state, v, g = step(x, state)
            v = float(v)  # the value at x
            if nit == 1:  # the start's value from the first step (no separate compilation of neg)
                start = -v
                if not np.isfinite(start):
                    raise ValueError("the central start violates a hard constraint (skull, inverted element)")
                best_f = v
            if np.isfinite(v) and v <= best_f:
                best_x, best_f = x, v
            f_new = float(optax.tree.get(state, "value"))
            if not np.isfinite(f_new):
                message = "line search found no feasible step"
                break
            x = x_new
            if f_new < best_f:
                best_x, best_f = x, f_new
            g_norm = float(jnp.linalg.norm(g))
            if f_new == v and g_norm > 1e-8:
                message = "no step: the line search found no feasible decrease (a hard constraint)"
                break
            if abs(v - f_new) <= 1e-10 * max(abs(f_new), 1.0) or g_norm <= 1e-8:
                message = "converged: relative reduction <= 1e-10 or gradient norm <= 1e-8"
                break
        out = theta.copy()
        out[sl] = np.asarray(best_x)[sl]  # (the rest unchanged: held by the mask)
        return out, start, SimpleNamespace(fun=best_f, nit=nit, message=message)

    # the parameters move in the coordinates x = log(phi - r1) (the same objective, no
    # Jacobian: this is the mode over phi): positive by construction, a step beyond r2 is
    # -inf (outside the line search's domain), and unlike the sampler's logit coordinates
    # the gradient does not vanish near the upper bound
    lo, hi = np.maximum(np.asarray(post.prior_r1), 0.0), np.asarray(post.prior_r2)
    margin = 1e-3

    def in_log(logdensity):
        def f(x, guess):
            phi = lo + jnp.exp(x[nb3:])
            return logdensity(jnp.concatenate([x[:nb3], phi]), guess)
        return f

    def clip(phi):  # parameters kept the relative margin inside their support
        return np.clip(phi, lo + margin * (hi - lo), hi - margin * (hi - lo))

    def to_log(theta):
        return np.concatenate([theta[:nb3], np.log(clip(theta[nb3:]) - lo)])

    def to_theta(x):
        return np.concatenate([x[:nb3], clip(lo + np.exp(x[nb3:]))])

    iters = cfg.init.optimizer_iterations
    x = to_log(theta0)
    objective = in_log(logdensity)
    if joint and post.n_free:  # stage 1: u_b alone at theta0's parameters
        x, start, res1 = maximise(objective, x, slice(0, nb3), max(iters // 2, 1))
        x, _, res = maximise(objective, x, free, max(iters - iters // 2, 1))
        nit = res1.nit + res.nit
    else:
        x, start, res = maximise(objective, x, free, iters)
        nit = res.nit
    info = {"logp_start": start, "logp_mode": -float(res.fun), "iterations": int(nit),
            "message": str(res.message), "parameters_optimized": bool(joint),
            "search_barrier_mm": search_barrier}
    if joint and cfg.model.prior_normaliser == "exact" and post.n_free:
        x, _, res_p = maximise(in_log(make_logdensity(problem, cfg)), x, slice(nb3, post.dim), 100)
        info.update(logp_mode=-float(res_p.fun), parameter_iterations_exact=int(res_p.nit))
    return (to_theta(x) if joint else np.concatenate([x[:nb3], theta0[nb3:]])), info


def start_check(problem: Problem, cfg: Config):
    """The jitted check of chain starts: ``(chains, dim) -> (chains,)`` log posterior.

    Each row is evaluated from a cold interior (zeros); ``-inf`` marks a start that violates
    a hard constraint (skull, inverted element, prior support) or whose solve did not
    converge.  :func:`start_center` and :func:`initial_positions` share it, so a run
    compiles one program for both (one compilation of 1.2-1.3 s fewer on the tests' tiny
    quickstart).
    """
    logdensity = make_logdensity(problem, cfg)
    zeros = jnp.zeros((problem.posterior.op.n_interior, 3))

    def start_logdensity(theta):
        return logdensity(theta, zeros)[0]

    return jax.jit(jax.vmap(start_logdensity))


def initial_positions(problem: Problem, cfg: Config, center, rng, prec=None, *,
                      check=None) -> np.ndarray:
    """Dispersed starts ``(chains, dim)`` around ``center``.

    ``u_b``: Gaussian jitter of ``init.perturb_mm`` (method ``between``), or
    ``init.overdispersion`` times a draw from the Laplace approximation ``N(0, prec^-1)``
    (method ``mode``).  Parameters: log-normal jitter ``init.param_jitter``, clipped into
    the prior support.  Starts that violate a hard constraint are redrawn closer to the
    centre (halving the jitter, at most 20 times).  ``check``: as in :func:`start_center`.

    Raises
    ------
    ValueError
        If some chain has no valid start after 20 halvings.
    """
    post = problem.posterior
    nb3 = 3 * post.n_boundary
    c = cfg.sampler.chains
    lo = np.asarray(post.prior_r1)
    hi = np.asarray(post.prior_r2)
    chol = None
    if cfg.init.method == "mode":
        chol = sla.cholesky(prec, lower=True)
    check = start_check(problem, cfg) if check is None else check
    out = np.tile(np.asarray(center, np.float64), (c, 1))
    todo = np.arange(c)
    shrink = 1.0
    for _ in range(20):
        z = rng.standard_normal((len(todo), nb3))
        if chol is None:
            du = cfg.init.perturb_mm * z
        else:
            du = cfg.init.overdispersion * sla.solve_triangular(chol, z.T, lower=True, trans="T").T
        phi = center[nb3:] * np.exp(cfg.init.param_jitter * rng.standard_normal((len(todo), post.n_free)))
        out[todo, :nb3] = center[:nb3] + shrink * du
        out[todo, nb3:] = np.clip(phi, lo + 1e-3 * (hi - lo), hi - 1e-3 * (hi - lo))
        ok = np.isfinite(np.asarray(check(jnp.asarray(out))))
        todo = np.flatnonzero(~ok)
        if todo.size == 0:
            return out
        shrink *= 0.5
    raise ValueError(f"could not find valid starts for chains {todo.tolist()}")


def _dofs(nodes):
    return (3 * np.asarray(nodes)[:, None] + np.arange(3)).ravel()


def laplace_precision(problem: Problem, theta) -> np.ndarray:
    """Gauss-Newton precision of ``u_b`` at ``theta`` with the parameters held fixed.

    ``P = 2 J^T J / T_s + S / T_r``: ``J`` is the Jacobian of the SSD residuals with respect
    to ``u_b`` through the interior map ``u_i = -K_ii^{-1} K_ib u_b``, ``S`` the Schur
    complement of ``K`` on the boundary DOFs (so ``E_r = u_b^T S u_b / 2``).  Returns the
    dense ``(3 n_b, 3 n_b)`` matrix.
    """
    post, mesh = problem.posterior, problem.mesh
    nb = len(mesh.boundary)
    phi = np.asarray(theta)[3 * nb:]
    lam_g, mu_g = (np.asarray(a) for a in elastic_groups(post, jnp.asarray(phi)))
    g = problem.element_group
    k = stiffness_matrix(mesh.nodes, mesh.tets, lam_g[g], mu_g[g]).tocsc()
    bd, idf = _dofs(mesh.boundary), _dofs(mesh.interior)
    k_ii, k_ib, k_bb = k[idf][:, idf], k[idf][:, bd], k[bd][:, bd]
    h = -spla.splu(sp.csc_matrix(k_ii)).solve(k_ib.toarray())  # (3 n_i, 3 n_b)
    schur = k_bb.toarray() + k_ib.T @ h
    # residual Jacobian w.r.t. nodal displacements, through the interior map
    u_b = np.asarray(theta)[: 3 * nb]
    u = np.zeros(3 * len(mesh.nodes))
    u[bd] = u_b
    u[idf] = h @ u_b
    u = u.reshape(-1, 3)
    term = post.ssd
    bary = np.asarray(term.bary)  # (Q, 4)
    nq = len(bary)
    u_q = np.einsum("qa,mad->mqd", bary, u[mesh.tets])
    y = np.asarray(term.points) + u_q
    grad_m = jax.jit(jax.vmap(jax.grad(lambda p: sample_moving(term, p))))(
        jnp.asarray(y.reshape(-1, 3))
    )
    grad_m = np.asarray(grad_m).reshape(len(mesh.tets), nq, 3)
    vals = -np.asarray(term.sqrt_w)[:, :, None, None] * bary[None, :, :, None] * grad_m[:, :, None, :]
    rows = np.broadcast_to(np.arange(nq * len(mesh.tets)).reshape(-1, nq)[:, :, None, None], vals.shape)
    cols = 3 * mesh.tets[:, None, :, None] + np.arange(3)[None, None, None, :]
    cols = np.broadcast_to(cols, vals.shape)
    jac = sp.csr_array((vals.ravel(), (rows.ravel(), cols.ravel())),
                       shape=(nq * len(mesh.tets), 3 * len(mesh.nodes)))
    # J_b^T J_b with J_b = J_b' + J_i H, through the sparse Gram matrix (J_b itself is dense
    # with one row per quadrature point: too large for a composite rule)
    gram = (jac.T @ jac).tocsr()
    g_ib = gram[idf][:, bd]
    jtj = gram[bd][:, bd].toarray() + g_ib.T @ h + h.T @ g_ib + h.T @ (gram[idf][:, idf] @ h)
    prec = 2.0 * float(post.inv_t_s) * jtj + float(post.inv_t_r) * schur
    prec = 0.5 * (prec + prec.T)
    ridge = 1e-6 * np.trace(prec) / len(prec)
    return prec + ridge * np.eye(len(prec))


def proposal_scale(problem: Problem, cfg: Config, prec=None):
    """Initial jumping-kernel scales ``(sigma_u, sigma_phi)`` of the two coordinate blocks.

    ``sigma_u``: for ``proposal: laplace`` the ``(3 n_b, 3 n_b)`` factor ``2.38 / sqrt(3 n_b)
    R^-T`` with ``prec = R R^T`` the Gauss-Newton precision of ``u_b``
    (:func:`laplace_precision`), i.e. proposal covariance ``2.38^2 / d prec^-1``; for
    ``isotropic`` the paper's ``sigma_u`` (Eq. 14) as a ``(3 n_b,)`` vector.
    ``sigma_phi``: ``sigma_lam`` / ``sigma_mu`` per free parameter, ``(n_free,)``.
    """
    post = problem.posterior
    s = cfg.sampler
    sig_p = np.array([s.sigma_lam if p == "lam" else s.sigma_mu for p, _ in problem.layout.free])
    nb3 = 3 * post.n_boundary
    if s.proposal == "isotropic":
        return np.full(nb3, s.sigma_u), sig_p
    chol = sla.cholesky(prec, lower=True)
    factor = sla.solve_triangular(chol, np.eye(nb3), lower=True, trans="T")  # R^-T
    return 2.38 / np.sqrt(nb3) * factor, sig_p


class Initialisation(NamedTuple):
    """Starts and jumping kernels of a run (saved with it, so a resumed run reuses them).

    Attributes
    ----------
    x0 : (C, dim)  chain starts
    center : (dim,)  central start (after the mode search, if any)
    sigma : tuple of arrays  initial jumping-kernel scale per block
    blocked : bool  u_b and the elastic parameters in separate blocks
    info : dict  how the starts were made (mode search figures, timings)
    """

    x0: np.ndarray
    center: np.ndarray
    sigma: tuple
    blocked: bool
    info: dict


def initialise(problem: Problem, cfg: Config) -> Initialisation:
    """Central start (:func:`start_center`), optional mode search, dispersed starts, kernels."""
    rng = np.random.default_rng(cfg.seed)
    t = time.perf_counter()
    check = start_check(problem, cfg)
    center, info = start_center(problem, cfg, check=check)
    info["method"] = cfg.init.method
    if cfg.init.method == "mode":
        center, mode_info = find_mode(problem, cfg, center)
        info.update(mode_info)
    prec = None
    if cfg.init.method == "mode" or cfg.sampler.proposal == "laplace":
        prec = laplace_precision(problem, center)
    x0 = initial_positions(problem, cfg, center, rng, prec, check=check)
    post = problem.posterior
    nb3 = 3 * post.n_boundary
    if cfg.sampler.gradient:
        # u_b = c + F w: F = R^-T with prec = R R^T (laplace), or 1 mm (isotropic)
        if cfg.sampler.proposal == "laplace":
            chol = sla.cholesky(prec, lower=True)
            factor = sla.solve_triangular(chol, np.eye(nb3), lower=True, trans="T")
        else:
            factor = np.ones(nb3)
        info["init_s"] = time.perf_counter() - t
        return Initialisation(x0, center, (factor, np.full(post.n_free, cfg.sampler.sigma_eta)), True, info)
    sigma_u, sigma_p = proposal_scale(problem, cfg, prec)
    info["init_s"] = time.perf_counter() - t
    if cfg.sampler.blocked:
        sigma = (sigma_u, sigma_p)
    elif sigma_u.ndim == 1:  # the paper's joint proposal (Eq. 14)
        sigma = (np.concatenate([sigma_u, sigma_p]),)
    else:
        joint = np.zeros((post.dim, post.dim))
        joint[:nb3, :nb3] = sigma_u * np.sqrt(nb3 / post.dim)
        joint[np.arange(nb3, post.dim), np.arange(nb3, post.dim)] = sigma_p
        sigma = (joint,)
    return Initialisation(x0, center, sigma, cfg.sampler.blocked, info)


def sample_problem(problem: Problem, cfg: Config, init: Initialisation | None = None, *,
                   on_chunk=None, resume=None, resume_draws=None) -> tuple[SamplerResult, Initialisation]:
    """Initialise (unless ``init`` is given) and sample.

    ``on_chunk``, ``resume`` and ``resume_draws`` are passed to
    :func:`bayesreg.sampler.sample` (checkpointing; see :func:`run`).

    Returns
    -------
    result : SamplerResult
    init : Initialisation
    """
    init = init or initialise(problem, cfg)
    post = problem.posterior
    nb3 = 3 * post.n_boundary
    if init.blocked:
        blocks, adapt = (np.arange(nb3), np.arange(nb3, post.dim)), (True, True)
    else:
        blocks, adapt = None, None

    def estimands(draws):
        # boundary coordinates, free parameters and the lam/mu ratios per group
        phi = draws[..., nb3:]
        lam_g, mu_g = (np.asarray(a) for a in elastic_groups(post, phi))
        return np.concatenate([draws, lam_g / mu_g], axis=-1)

    s = cfg.sampler
    if s.gradient:
        target = make_target(post, center_u=init.center[:nb3], factor=init.sigma[0],
                             exact=cfg.model.prior_normaliser == "exact", condensed=s.use_condensed,
                             rtol=cfg.solver.rtol, maxiter=cfg.solver.maxiter,
                             precondition=dense_preconditioning(problem, cfg))
        result = sample_gradient(
            jax.random.key(cfg.seed), target, init.x0, jnp.zeros((post.op.n_interior, 3)),
            kind=s.kind, step_size=s.step_size, eta_scale=init.sigma[1], dense_mass=s.dense_mass,
            adapt_mass=s.adapt_mass, elastic_moves=s.elastic_moves,
            num_integration_steps=s.hmc_steps, jitter_integration_steps=s.hmc_jitter,
            max_tree_depth=s.max_tree_depth,
            thinning=s.thinning, warmup_steps=s.warmup_steps, max_draws=s.max_draws,
            min_draws=s.min_draws, chunk_draws=s.chunk_draws, target_acceptance=s.target_acceptance,
            rhat_threshold=s.rhat_threshold, rhat_split=s.rhat_split, estimands=estimands,
            progress=cfg.output.progress, on_chunk=on_chunk, resume=resume, resume_draws=resume_draws,
        )
        return result, init
    condensation = _condensed_rw(problem, cfg) if init.blocked and s.use_condensed else None
    preconditioner = _preconditioner_rw(problem, cfg) if dense_preconditioning(problem, cfg) else None
    result = sample(
        jax.random.key(cfg.seed),
        make_logdensity(problem, cfg),
        init.x0,
        jnp.zeros((post.op.n_interior, 3)),
        tuple(init.sigma),
        blocks=blocks,
        adapt_diagonal=adapt,
        thinning=s.thinning,
        warmup_steps=s.warmup_steps,
        max_draws=s.max_draws,
        min_draws=s.min_draws,
        chunk_draws=s.chunk_draws,
        target_acceptance=s.target_acceptance or 0.25,
        rhat_threshold=s.rhat_threshold,
        rhat_split=s.rhat_split,
        estimands=estimands,
        progress=cfg.output.progress,
        on_chunk=on_chunk,
        resume=resume,
        resume_draws=resume_draws,
        condensation=condensation,
        preconditioner=preconditioner,
    )
    return result, init


def run(config=None, *, out=None, overrides=None, overwrite=None, progress=None, resume=None):
    """Run the whole job and write its run directory.

    Parameters
    ----------
    config : Config, str or Path
        A validated config or the path of a YAML file (not needed with ``resume``).
    out : str or Path, optional
        Run directory (default ``output.dir`` of the config).
    overrides : list of str, optional
        ``key.sub=value`` overrides (as ``--set``).
    overwrite : bool, optional
        Replace an existing run directory (default ``output.overwrite``).
    progress : bool, optional
        Progress bar (default ``output.progress``).
    resume : str or Path, optional
        Continue the unfinished run in this directory, with its saved config, problem (mesh,
        images, truth), starts and sampler state: the result equals that of the run never
        interrupted (same draws).  ``config`` and ``overrides`` must then be omitted.

    Returns
    -------
    bayesreg.outputs.RunResult

    A new run that fails before its sampling starts (an error in the data, the mesh or the
    starts) removes its run directory and puts back the one it replaced; one that fails or
    is interrupted later keeps its checkpoint for ``resume``.

    Raises
    ------
    FileExistsError
        If the run directory exists and is not empty and ``overwrite`` is false (or it is
        not a run directory), or a run to resume is already finished.
    FileNotFoundError
        If ``resume`` names a directory without a checkpoint.
    ConfigError
        On a bad config, override or saved config (the message names the key or file).
    """
    from bayesreg.checkpoint import Checkpoint
    from bayesreg.outputs import RunDirectory, write_outputs

    t0 = time.perf_counter()
    if resume is not None:
        if config is not None or overrides or out is not None or overwrite:
            raise ValueError("resume continues a run with its own config and directory: give no "
                             "config, overrides, out or overwrite")
        run_dir = RunDirectory(resume, resume=True)
        ckpt = Checkpoint(run_dir.path)
        cfg = ckpt.load_config()
        cfg.output.dir = run_dir.path
    else:
        from bayesreg.config import override_config

        cfg = config if isinstance(config, Config) else load_config(config, overrides=overrides)
        values = {k: v for k, v in (("output__dir", None if out is None else str(out)),
                                    ("output__overwrite", overwrite)) if v is not None}
        # a copy (the caller's config is not changed), overrides applied to a Config object
        cfg = override_config(cfg, overrides if isinstance(config, Config) else None, **values)
        inputs = {"data.fixed": cfg.data.fixed, "data.moving": cfg.data.moving,
                  "data.labels": cfg.data.labels, "mesh.file": cfg.mesh.file}
        run_dir = RunDirectory(cfg.output.dir, overwrite=cfg.output.overwrite,  # fails early
                               inputs={k: v for k, v in inputs.items() if v is not None})
        ckpt = Checkpoint(run_dir.path)
        if cfg.output.checkpoint:
            ckpt.save_config(cfg)
    if progress is not None:
        cfg.output.progress = progress

    try:
        saved = resume is not None and ckpt.problem_path.is_file()
        problem = load_problem(ckpt.problem_path, cfg) if saved else prepare(cfg)
        if cfg.output.checkpoint and not saved:
            save_problem(problem, ckpt.problem_path)
        init = ckpt.load_init() if resume is not None else None
        if init is None:
            init = initialise(problem, cfg)
            if cfg.output.checkpoint:
                ckpt.save_init(init)
    except Exception:
        # a new run that fails before its sampling starts (bad data, a mesh that fails, no
        # valid start) leaves nothing behind and puts back what it replaced, so the same
        # command runs again once the input is fixed (an interrupt keeps it for --resume)
        if resume is None:
            run_dir.rollback()
        raise
    state = ckpt.load_state() if resume is not None else None
    result, init = sample_problem(
        problem, cfg, init,
        on_chunk=ckpt.on_chunk if cfg.output.checkpoint else None,
        resume=None if state is None else state[0],
        resume_draws=None if state is None else state[1],
    )
    init_info = dict(init.info)
    timings = {**problem.timings, "init_s": init_info.pop("init_s", float("nan")), **result.timings,
               "total_before_outputs_s": time.perf_counter() - t0}
    res = write_outputs(run_dir, cfg, problem, result, init, timings, init_info,
                        resumed=resume is not None)
    ckpt.clear_progress()
    return res

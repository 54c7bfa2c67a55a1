"""A registration problem: images, labels, mesh, synthetic truth and the posterior.

:func:`make_data` does the expensive, non-reproducible part (reading or making the
images, meshing, the synthetic truth) and returns a :class:`ProblemData`;
:func:`assemble` builds the parameter layout, the priors and the posterior of it
(:func:`bayesreg.model.posterior.build_posterior`) into a :class:`Problem`; :func:`prepare` does
both.  A run stores its :class:`ProblemData` (:mod:`bayesreg.checkpoint`) so that a resumed
run reuses the mesh.
"""

from __future__ import annotations

import contextlib
import hashlib
import time
import warnings
from pathlib import Path
from typing import NamedTuple

import jax.numpy as jnp
import numpy as np
import scipy.ndimage as ndi

from bayesreg.data import labels as L
from bayesreg.config import Config
from bayesreg.mesh.constraints import points_forbidden, skull_constraint
from bayesreg.truth.contact import constrained_shift
from bayesreg.data.datasets import brainweb, brainweb_model, mni152
from bayesreg.data.images import (
    Image, check_same_frame, interpolate_numpy, load_nifti, pad, resample, resample_to_spacing,
    to_reference_grid)
from bayesreg._checks import count_nonfinite
from bayesreg.mesh.tetmesh import Mesh, boundary_nodes, read_mesh, signed_volumes
from bayesreg.mesh.meshing import carve_skull, mesh_brain, mesh_brain_sized
from bayesreg.model.parameters import ParamLayout
from bayesreg.model.posterior import Posterior, build_posterior, orthogonal_discrepancy
from bayesreg.model.lncc import build_lncc
from bayesreg.model.similarity import build_ssd
from bayesreg.stages import Stages
from bayesreg.truth.synthetic import (Truth, brain_shift, bump_field, field_truth, random_field,
                                      with_discrepancy)
from bayesreg.interop.transforms import load_displacement
from bayesreg.mesh.warp import warp_image, warp_image_field

__all__ = ["ProblemData", "Problem", "make_data", "assemble", "prepare", "parameter_layout",
           "sampled_mesh", "similarity_term"]


SYNTHETIC_ORDER = 3
"""Spline order of ``f``'s interpolation when a synthetic truth warps it into ``m``
(:func:`bayesreg.mesh.warp.warp_image`): the cubic B-spline.  Trilinear resampling left ``E_s =
459`` at the quickstart's truth against 217 (the model reads ``m`` trilinearly either way),
a misfit the posterior paid with a biased GM ratio (8.61-9.67 against the truth 10)."""


class ProblemData(NamedTuple):
    """The data of a problem: what :func:`make_data` makes and a checkpoint stores.

    Attributes
    ----------
    f, m : Image
        Pre- and intra-operative images, intensities divided by ``intensity_scale``.
    labels : Image
        Label map in the internal coding (:mod:`bayesreg.data.labels`), carved around the mesh.
    mesh : Mesh
    truth : Truth or None
        The synthetic truth (synthetic cases).
    truth_info : dict or None
        How the truth was made (the constrained minimiser's figures).
    intensity_scale : float
        ``f`` and ``m`` were divided by it.
    n_skull_carved : int
        Skull voxels freed next to the mesh (:func:`bayesreg.mesh.meshing.carve_skull`).
    timings : dict
        Seconds of each stage.
    mesh_info : dict or None
        How the mesh was made: its edge length (mm) and, with ``mesh.target_nodes``, the
        attempts; with ``mesh.file``, the file and its SHA-256.
    """

    f: Image
    m: Image
    labels: Image
    mesh: Mesh
    truth: Truth | None
    truth_info: dict | None
    intensity_scale: float
    n_skull_carved: int
    timings: dict
    mesh_info: dict | None = None


class Problem(NamedTuple):
    """Everything needed to sample and to report one registration problem.

    Attributes
    ----------
    f, m, labels, truth : as in :class:`ProblemData`
    mesh : Mesh
        The mesh as the posterior samples it: ``boundary`` the sampled nodes, the surface
        (``model.interior: solve``) or every node (``sample``; :func:`sampled_mesh`).
    layout : ParamLayout
        The elastic parameters' groups, free and fixed parameters.
    element_group : (M,) int
        Parameter group of each element.
    posterior : Posterior
    phi_true : (n_free,) or None
        True free parameters, where defined (synthetic cases with per-tissue groups).
    phi_init : (n_free,)
        Central start of the elastic parameters (``model.initial_*``).
    intensity_scale, n_skull_carved, timings, truth_info, mesh_info : as in :class:`ProblemData`
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

    @property
    def data(self) -> ProblemData:
        """The :class:`ProblemData` this problem was assembled from (its mesh's ``boundary``
        the surface nodes, whatever the posterior samples)."""
        mesh = self.mesh._replace(boundary=boundary_nodes(self.mesh.tets))
        return ProblemData(self.f, self.m, self.labels, mesh, self.truth, self.truth_info,
                           self.intensity_scale, self.n_skull_carved, self.timings, self.mesh_info)


def _load_data(cfg: Config):
    """``f``, ``m`` (or None) and the labels of ``cfg.data``, padded by ``4 skull_margin_mm``
    (images with 0, labels with skull), whose free space is the shell of ``skull_margin_mm``
    around the intracranial tissues for every source (:func:`bayesreg.data.labels.free_shell`)."""
    f, m, labels = _read_data(cfg)
    labels, _ = L.free_shell(labels, cfg.data.skull_margin_mm)
    L.check_labels(labels)
    return f, m, labels


def _read_data(cfg: Config):
    d = cfg.data
    margin = 4 * d.skull_margin_mm
    if d.source == "mni152":
        t1, gm, wm, mask = mni152(d.resolution_mm or 1.0, margin_mm=margin)
        labels = L.labels_from_probabilities(gm, wm, mask, skull_margin_mm=d.skull_margin_mm)
        return t1, None, labels
    if d.source == "brainweb":
        which = {"path": d.subject} if isinstance(d.subject, Path) else {"subject": d.subject}
        model = brainweb_model(**which, directory=d.brainweb_dir)
        t1, labels = brainweb(model, resolution_mm=d.resolution_mm or 0.5,
                              noise_percent=d.noise_percent, seed=cfg.seed, margin_mm=margin)
        return t1, None, labels
    f = load_nifti(d.fixed)
    lab = load_nifti(d.labels)
    m = load_nifti(d.moving) if d.moving is not None else None
    for key, img in (("data.fixed", f), ("data.labels", lab), ("data.moving", m)):
        bad = 0 if img is None else count_nonfinite(img.data)
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
    # leaving the image is forbidden: the padding is skull, so that a brainstem cut by the
    # image's edge stays closed
    labels = pad(L.remap_labels(lab, d.label_coding), margin, value=L.SKULL)
    f = pad(f, margin)
    m = pad(m, margin) if m is not None else None
    return f, m, labels


def parameter_layout(cfg: Config, mesh: Mesh) -> tuple[ParamLayout, np.ndarray]:
    """The elastic parameters' layout (``model.elastic``, ``model.fixed``) on ``mesh`` and the
    parameter group of each element ``(M,)``.

    Raises
    ------
    ValueError
        ``model.fixed.group`` is not one of the groups.
    """
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


def _truth_line(info: dict, u) -> str:
    """One line on a synthetic truth: its kind, push, largest displacement, for the
    constrained truth its active sets and energy, and the field added to an FE truth."""
    if info["truth"] in ("bump", "random", "field"):
        line = f"{info['truth']} (not made by the model)"
        if info["truth"] == "bump":
            line += f", peak {info['shift_mm']:g} mm, sd {info['radius_mm']:g} mm"
        if info["truth"] == "random":
            line += f", smoothing sd {info['length_mm']:g} mm, seed {info['seed']}"
        return line + f", max |u| at the nodes {float(np.linalg.norm(u, axis=1).max()):.1f} mm"
    line = (f"{info['truth']}, {len(info['pushed'])} nodes pushed {info['shift_mm']:g} mm, "
            f"max |u| {float(np.linalg.norm(u, axis=1).max()):.1f} mm")
    if info["truth"] == "constrained":
        line += (f", {info['n_active']} skull and {info['n_volume_active']} volume constraints "
                 f"active, energy {info['energy']:.4g}")
    if "discrepancy" in info:
        d = info["discrepancy"]
        line += (f", plus a {'volume-preserving ' if d['solenoidal'] else ''}random field of "
                 f"{d['shift_mm']:g} mm (smoothing sd {d['length_mm']:g} mm, not made by the model)")
    return line


def _make_truth(cfg: Config, mesh: Mesh, labels: Image):
    """Synthetic truth per ``cfg.synthetic``; returns ``(Truth, info dict)``.

    A dense truth (``bump``, ``random``, ``field``) lies on ``labels``' grid (``f``'s).

    Raises
    ------
    ValueError
        If the constrained minimiser does not converge, or the truth puts a node in the
        skull region or inverts an element (nothing is hidden: the figures are in the message).
    """
    s = cfg.synthetic
    if s.truth in ("bump", "random", "field"):
        if s.truth == "bump":
            field = bump_field(labels, mesh, shift_mm=s.shift_mm, n_pushed=s.n_pushed,
                               radius_mm=s.falloff_mm)
            info = {"truth": "bump", "shift_mm": s.shift_mm, "radius_mm": s.falloff_mm}
        elif s.truth == "random":
            field = random_field(labels, mesh, shift_mm=s.shift_mm, length_mm=s.falloff_mm,
                                 seed=cfg.seed, solenoidal=s.solenoidal)
            info = {"truth": "random", "shift_mm": s.shift_mm, "length_mm": s.falloff_mm,
                    "seed": cfg.seed, "solenoidal": s.solenoidal}
        else:
            given = load_displacement(s.field)
            field = Image(np.stack([resample(Image(given.data[..., c], given.affine), labels.affine,
                                             labels.data.shape, order=1).data for c in range(3)], -1),
                          labels.affine)
            info = {"truth": "field", "file": str(s.field), "sha256": _sha256(s.field)}
        truth = field_truth(mesh, field, n_pushed=s.n_pushed)
        info["pushed"] = truth.pushed.tolist()
        _check_truth_nodes(truth, mesh, labels, info)
        return truth, info
    lam_t = np.array([s.lam.csf, s.lam.gm, s.lam.wm])[mesh.tissue]
    mu_t = np.array([s.mu.csf, s.mu.gm, s.mu.wm])[mesh.tissue]
    pushed = None if s.pushed_nodes is None else np.asarray(s.pushed_nodes, np.int64)
    if s.truth == "constrained":
        forbidden = Image((labels.data == L.SKULL).astype(np.uint8), labels.affine)
        truth, info = constrained_shift(
            mesh, lam_t, mu_t, forbidden, shift_mm=s.shift_mm, n_pushed=s.n_pushed, pushed=pushed,
            clearance_mm=s.clearance_mm, tol_mm=s.tol_mm, min_volume_ratio=s.min_volume_ratio,
        )
        if not info["converged"] or info["n_forbidden_nodes"] or info["n_inverted"]:
            raise ValueError(
                "the constrained ground truth failed on {data}: converged {converged} (the push "
                "reached {load_factor:.0%} in {load_steps} load steps), max "
                "violation {max_violation_mm:.3g} mm (tol {tol_mm}), nodes in the skull "
                "{n_forbidden_nodes}, inverted elements {n_inverted}, smallest volume ratio "
                "{min_volume_ratio:.3g}; try another mesh (mesh.file, or meshing again), a "
                "larger data.skull_margin_mm or a smaller synthetic.shift_mm".format(
                    data=_data_name(cfg), **info)
            )
    else:
        if pushed is not None:
            raise ValueError("synthetic.pushed_nodes needs synthetic.truth: constrained")
        truth = brain_shift(mesh, lam_t, mu_t, shift_mm=s.shift_mm, n_pushed=s.n_pushed,
                            falloff_mm=s.falloff_mm)
        info = {"truth": "smooth", "shift_mm": s.shift_mm, "pushed": truth.pushed.tolist()}
        # the constrained minimiser checks both itself; the smooth push is not constrained
        _check_truth_nodes(truth, mesh, labels, info)
    info.setdefault("truth", s.truth)
    info["lam"] = s.lam.model_dump()
    info["mu"] = s.mu.model_dump()
    if s.discrepancy_mm > 0:  # a part of the shift no FE field makes, on top
        extra = random_field(labels, mesh, shift_mm=s.discrepancy_mm,
                             length_mm=s.discrepancy_length_mm, seed=cfg.seed,
                             solenoidal=s.solenoidal)
        truth = with_discrepancy(truth, mesh, extra)
        info["discrepancy"] = {"shift_mm": s.discrepancy_mm, "length_mm": s.discrepancy_length_mm,
                               "seed": cfg.seed, "solenoidal": s.solenoidal}
        _check_truth_nodes(truth, mesh, labels, info)
        if info["n_inverted"]:
            raise ValueError(f"the FE truth plus the {s.discrepancy_mm:g} mm random field inverts "
                             f"{info['n_inverted']} element(s): lower synthetic.discrepancy_mm or "
                             "raise synthetic.discrepancy_length_mm")
    return truth, info


def _check_truth_nodes(truth, mesh: Mesh, labels: Image, info: dict) -> None:
    """A truth that is not the constrained minimiser must keep every node out of the skull
    region as the samplers see it (:func:`bayesreg.mesh.constraints.points_forbidden`;
    ``ValueError`` otherwise); its inverted elements are counted in ``info``."""
    skull = skull_constraint(Image((labels.data == L.SKULL).astype(np.uint8), labels.affine),
                             nodes=mesh.nodes)
    bad = np.asarray(points_forbidden(skull, jnp.asarray(mesh.nodes + truth.u)))
    if np.any(bad):
        raise ValueError(
            f"the synthetic truth moves {int(np.sum(bad))} node(s) into the "
            "skull region; lower synthetic.shift_mm (or synthetic.discrepancy_mm) or widen "
            "data.skull_margin_mm"
        )
    info["n_inverted"] = int(np.sum(signed_volumes(mesh.nodes + truth.u, mesh.tets) <= 0))


def _data_name(cfg: Config) -> str:
    """The data of ``cfg`` in a few words (for messages)."""
    d = cfg.data
    if d.source == "brainweb":
        return f"BrainWeb {'subject ' + str(d.subject) if isinstance(d.subject, int) else d.subject}"
    return "the MNI152 brain" if d.source == "mni152" else str(d.fixed)


def _sha256(path) -> str:
    """Hex SHA-256 of a file's bytes (recorded with a run's ``mesh.file``)."""
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def make_data(cfg: Config, stages: Stages | None = None) -> ProblemData:
    """The expensive, non-reproducible part of :func:`prepare`: images, labels, mesh, truth.

    Intensities of ``f`` and ``m`` are divided by the ``data.intensity_percentile``-th
    percentile of ``f`` inside the intracranial volume (about [0, 1] afterwards), so that
    ``E_s`` and ``T_s`` have image-independent units (``intensity^2 mm^3``).  With a
    synthetic case, ``m`` is ``f`` warped exactly through the FE map of the truth.

    Parameters
    ----------
    cfg : Config
    stages : Stages, optional
        Tracks the stages ``data``, ``mesh`` and ``truth`` (:mod:`bayesreg.stages`: their
        errors name them).

    Returns
    -------
    ProblemData

    Raises
    ------
    FileNotFoundError
        A data file or ``mesh.file`` does not exist.
    MeshError
        Meshing fails, or ``mesh.file`` is unusable (:func:`bayesreg.mesh.tetmesh.read_mesh`).

    Warns
    -----
    UserWarning
        Nodes of ``mesh.file`` lie in the skull region of the label map at rest: the skull
        voxels under and near the mesh become background (:func:`bayesreg.mesh.meshing.carve_skull`,
        as for a generated mesh that pokes past the brain mask), which a given mesh should
        not need.
    """
    timings = {}
    stage = stages.stage if stages is not None else (lambda name: contextlib.nullcontext())
    tell = stages.tell if stages is not None else (lambda detail: None)
    with stage("data"):
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
        spacing = np.linalg.norm(f.affine[:3, :3], axis=0)
        tell(f"{_data_name(cfg)}, f {'x'.join(map(str, f.data.shape[:3]))} voxels of "
             f"{'x'.join(f'{v:.3g}' for v in spacing)} mm, "
             f"m {'from the synthetic truth' if m is None else 'given'}")

    with stage("mesh"):
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
        tell(f"{len(mesh.nodes)} nodes ({len(mesh.boundary)} boundary), {len(mesh.tets)} tets"
             + (f", {n_carved} skull voxels carved" if n_carved else ""))
        empty = [n for n, c in zip(L.TISSUES, np.bincount(mesh.tissue, minlength=3)) if c == 0]
        if cfg.model.elastic == "tissue" and empty:
            raise ValueError(f"no mesh element is labelled {empty}: refine the mesh or use elastic: uniform")

    truth = truth_info = None
    t = time.perf_counter()
    if cfg.synthetic.enabled:
        with stage("truth"):
            truth, truth_info = _make_truth(cfg, mesh, labels)
            tell(_truth_line(truth_info, truth.u))
            if truth.field is not None:
                m = warp_image_field(f, truth.field, background=0.0, order=SYNTHETIC_ORDER)
            else:
                m = warp_image(f, mesh, truth.u, background=0.0, outside=cfg.synthetic.outside,
                               order=SYNTHETIC_ORDER)
    elif m is None:  # pragma: no cover - guarded by the config validator
        raise ValueError("no intra-operative image")
    timings["synthetic_s"] = time.perf_counter() - t
    return ProblemData(f, m, labels, mesh, truth, truth_info, scale, n_carved, timings, mesh_info)


def sampled_mesh(cfg: Config, mesh: Mesh) -> Mesh:
    """``mesh`` with ``boundary`` the nodes the posterior samples: its surface nodes
    (``model.interior: solve``, the paper's) or every node (``model.interior: sample``: no
    interior solve, the whole ``u`` under the elastic prior)."""
    if cfg.model.interior == "sample":
        return mesh._replace(boundary=np.arange(len(mesh.nodes), dtype=np.int64))
    return mesh


def similarity_term(cfg: Config, mesh: Mesh, f: Image, m: Image, reach: Image):
    """The similarity term ``model.similarity`` selects, for a mesh and an image pair:
    :func:`bayesreg.model.similarity.build_ssd` or :func:`bayesreg.model.lncc.build_lncc`."""
    common = dict(quadrature_level=cfg.model.quadrature_level, reach=reach,
                  moving_dtype=cfg.model.moving_dtype, interpolation=cfg.model.interpolation)
    if cfg.model.similarity == "lncc":
        lc = cfg.model.lncc
        return build_lncc(mesh.nodes, mesh.tets, f, m, window_mm=lc.window_mm, eps=lc.eps, **common)
    return build_ssd(mesh.nodes, mesh.tets, f, m, **common)


def assemble(cfg: Config, data: ProblemData) -> Problem:
    """Build the parameter layout, priors and posterior of :func:`make_data`'s output.

    With ``data.smoothing_mm > 0`` the posterior's copies of ``f`` and ``m`` are smoothed
    by a Gaussian of that sigma (``m`` was made from the unsmoothed ``f``).
    """
    f, m, labels, mesh, truth = data.f, data.m, data.labels, sampled_mesh(cfg, data.mesh), data.truth
    layout, group = parameter_layout(cfg, mesh)

    def free_values(lam_tv, mu_tv):
        lam_g = _group_values(layout, lam_tv, group, mesh)
        mu_g = _group_values(layout, mu_tv, group, mesh)
        return np.array([(lam_g if p == "lam" else mu_g)[g] for p, g in layout.free])

    phi_init = free_values(cfg.model.initial_lam, cfg.model.initial_mu)
    phi_true = None
    if truth is not None and truth.parameters_known and layout.group_names != ("all",):
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
        mesh, similarity_term(cfg, mesh, f_s, m_s, reach), forbidden,
        t_s=cfg.model.t_s if cfg.model.similarity == "ssd" else cfg.model.lncc.t_s,
        t_r=cfg.model.t_r, layout=layout, element_group=group,
        t_s_prior=(None if cfg.model.t_s_prior is None
                   else (cfg.model.t_s_prior.shape, cfg.model.t_s_prior.rate)),
        prior=prior, phi_ref=phi_init, barrier_mm=cfg.model.skull_barrier_mm,
        spectral=choice in ("auto", "spectral"),
        discrepancy=(None if cfg.model.discrepancy == "none" else
                     (cfg.model.discrepancy_prior.shape, cfg.model.discrepancy_prior.floor_mm,
                      cfg.model.discrepancy_prior.modes if cfg.model.discrepancy == "modes"
                      else None)),
    )
    return Problem(f, m, labels, mesh, layout, group, post, truth, phi_true, phi_init,
                   data.intensity_scale, data.n_skull_carved, dict(data.timings),
                   data.truth_info, data.mesh_info)


def prepare(cfg: Config) -> Problem:
    """Load data, derive labels, mesh, make the synthetic truth (if enabled), build the posterior
    (:func:`make_data` then :func:`assemble`).

    Raises
    ------
    FileNotFoundError, MeshError, ValueError
        As :func:`make_data` and :func:`assemble`.

    Examples
    --------
    The problem of the quickstart on a coarse mesh (the MNI152 template ships with nilearn):

    >>> import bayesreg
    >>> from bayesreg.model.problem import prepare
    >>> bayesreg.configure_jax()
    >>> cfg = bayesreg.load_config("configs/quickstart.yaml",
    ...                            overrides=["data.resolution_mm=3.0", "mesh.edge_length_mm=26"])
    >>> problem = prepare(cfg)
    >>> problem.layout.free_names
    ['lam_csf', 'lam_gm', 'lam_wm', 'mu_csf', 'mu_wm']
    >>> problem.posterior.dim == 3 * len(problem.mesh.boundary) + 5
    True
    """
    return assemble(cfg, make_data(cfg))


def at_start(problem: Problem, cfg: Config, anchor) -> Problem:
    """The problem as a run samples it: with ``model.discrepancy_prior.orthogonal`` the
    posterior's discrepancy made orthogonal to the FE interior's sensitivities at the
    boundary displacement ``anchor`` (:func:`bayesreg.model.posterior.orthogonal_discrepancy`);
    otherwise, or where it already is, ``problem`` itself.

    Parameters
    ----------
    problem : Problem
    cfg : Config
    anchor : (n_b, 3) array or Initialisation
        ``u_b`` in mm, or a run's :class:`~bayesreg.inference.initialisation.Initialisation`,
        saved with it: its ``anchor`` (the mode search's ``u_b`` before it went on under
        the orthogonal model), else its central start's ``u_b``.  So a resumed run and its
        outputs sample and report the same posterior.

    Raises
    ------
    ValueError
        As :func:`~bayesreg.model.posterior.orthogonal_discrepancy`, the stage named (a start
        that does not displace the tissue, an ``anchor`` of another shape).
    """
    post = problem.posterior
    if (not cfg.model.discrepancy_prior.orthogonal or post.discrepancy is None
            or post.discrepancy.sensitivities is not None):
        return problem
    if hasattr(anchor, "center"):
        anchor = (anchor.center[:3 * post.n_boundary].reshape(-1, 3) if anchor.anchor is None
                  else anchor.anchor)
    try:
        post = orthogonal_discrepancy(post, anchor)
    except ValueError as exc:
        raise ValueError(f"model.discrepancy_prior.orthogonal: {exc}") from exc
    return problem._replace(posterior=post)

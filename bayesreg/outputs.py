"""Run directory: ArviZ posterior, summaries, displacement maps, plots and ``run.json``.

Files of one run (all written atomically; an existing non-empty run directory is never
replaced unless ``overwrite`` is set; a run in progress keeps its draws in ``checkpoint/``,
see :mod:`bayesreg.checkpoint`):

==============================  ======================================================
``posterior.nc``                ArviZ DataTree (NetCDF): ``u_b`` (chain, draw, node, axis)
                                mm, ``lam``, ``mu``, ``ratio = lam/mu`` (chain, draw,
                                group); sample stats ``acceptance_rate``, ``lp``,
                                ``cg_iterations``, ``solve_failures``
``summary.csv``                 mean, sd, 90% central credible interval (``eti90_lb``,
                                ``eti90_ub``), ESS, rank R-hat (ArviZ), classic R-hat
``displacement_mean.nii.gz``    posterior mean of ``u`` on the image grid, (I, J, K, 3) mm
``displacement_sd.nii.gz``      posterior sd of each component of ``u``, (I, J, K, 3) mm
``displacement_norm_sd.nii.gz``   posterior sd of ``|u|``, (I, J, K) mm
``displacement_norm_iqr.nii.gz``  posterior inter-quartile range of ``|u|``, (I, J, K) mm
``displacement_init.nii.gz``    the chains' central start, (I, J, K, 3) mm
``displacement_true.nii.gz``    the synthetic truth (synthetic runs), (I, J, K, 3) mm
``mesh_mask.nii.gz``            voxels inside the undeformed mesh (where the maps are defined)
``mesh.vtu``                    mesh with point data ``u_mean``, ``u_sd``, ``u_norm_sd``,
                                ``u_norm_iqr``, ``u_init``, ``u_true``, ``u_error``; cell
                                data ``tissue``
``f.nii.gz``, ``m.nii.gz``, ``labels.nii.gz``  the (scaled) images and label map used
``trace.png``, ``marginals.png``  trace and marginal plots of the elastic parameters
``uncertainty.png``             IQR of ``|u|`` over ``f`` on three orthogonal slices
``errors.json``                 error of the posterior mean and of the start against the
                                truth, coverage of the credible intervals (synthetic)
``run.json``                    resolved config, seed, versions, timings, acceptance, CG,
                                R-hat, how the truth and the starts were made
``checkpoint/``                 config, problem (images, mesh, truth), starts; while the
                                run goes also the draws so far and the sampler state
==============================  ======================================================

Maps on the image grid are the FE interpolation of the nodal values (zero outside the mesh).
"""

from __future__ import annotations

import glob
import json
import os
import warnings
import platform
import shutil
import uuid
from importlib import metadata
from pathlib import Path
from typing import NamedTuple

import numpy as np

from bayesreg._files import fsync_dir, fsync_file, replace_durably
from bayesreg.images import Image, save_nifti

__all__ = ["RunDirectory", "RunResult", "write_outputs", "error_table", "format_report"]


class RunDirectory:
    """A run directory, written in place while the run goes and never overwritten silently.

    The run's checkpoint (:class:`bayesreg.checkpoint.Checkpoint`) lives in
    ``path/checkpoint``; final outputs are staged in ``path/.outputs-partial`` and moved in
    by :meth:`commit`, ``run.json`` last (its presence marks a finished run).

    Parameters
    ----------
    path : str or Path
    overwrite : bool
        Replace an existing non-empty directory that holds one of ``marks`` (a folder of
        other files is never replaced): it is moved aside to a hidden sibling
        (``.NAME.replaced-PID-XXXXXXXX``, unique per call) at once and deleted only when the new run commits;
        :meth:`rollback` puts it back.  A run interrupted after its sampling started keeps
        the sibling; the next run into ``path`` that commits (its ``--resume``, or another
        ``overwrite``) deletes it.
    resume : bool
        Continue the unfinished run in ``path`` (it must hold ``checkpoint/config.json`` and
        no ``run.json``).
    marks : tuple of str
        Names whose presence in ``path`` makes it a directory ``overwrite`` may replace
        (default: a run's ``run.json`` and ``checkpoint``, and the staging folder
        ``.outputs-partial`` that a run without checkpoints killed while writing its
        outputs leaves).
    inputs : dict, optional
        ``{name: path}`` of files the run still has to read (data, a given mesh): none may
        lie inside a directory that ``overwrite`` replaces (it moves aside at once).

    Raises
    ------
    FileExistsError
        If ``path`` exists, is not empty and neither ``overwrite`` nor ``resume`` is set;
        with ``overwrite``, if it holds none of ``marks``; with ``resume``, if the run there
        is already finished.
    NotADirectoryError
        If ``path`` or one of its parents is a file.
    ValueError
        With ``overwrite``, if one of ``inputs`` lies inside the directory to replace (named).
    FileNotFoundError
        With ``resume``, if ``path`` holds no checkpoint.
    """

    def __init__(self, path, *, overwrite=False, resume=False,
                 marks=("run.json", "checkpoint", ".outputs-partial"), inputs=None):
        self.path = Path(path)
        self.overwrite = overwrite
        self._old: Path | None = None
        # directories replaced by earlier --overwrite runs into this path that were
        # interrupted after their sampling started: deleted when this run commits
        self._stale = sorted(self.path.parent.glob(f".{glob.escape(self.path.name)}.replaced-*"))
        for p in (self.path, *self.path.parents):
            if p.exists() and not p.is_dir():
                raise NotADirectoryError(f"run directory {self.path}: {p} is a file")
        self._created = not self.path.exists()
        if resume:
            if (self.path / "run.json").is_file():
                raise FileExistsError(f"run {self.path} is finished (run.json exists): nothing to resume")
            if not (self.path / "checkpoint" / "config.json").is_file():
                raise FileNotFoundError(f"{self.path} holds no checkpoint/config.json: nothing to resume")
        elif self.path.exists() and any(self.path.iterdir()):
            if not overwrite:
                hint = (" (an unfinished run: continue it with --resume)"
                        if (self.path / "checkpoint").is_dir() and not (self.path / "run.json").exists()
                        else "")
                raise FileExistsError(
                    f"run directory {self.path} exists and is not empty{hint}; pass --out to "
                    "choose another or --overwrite to replace it"
                )
            if not any((self.path / m).exists() for m in marks):
                raise FileExistsError(
                    f"{self.path} is not empty and holds none of {', '.join(marks)}: not a "
                    "directory bayesreg wrote, so --overwrite does not replace it; choose "
                    "another --out"
                )
            if self.path.resolve() in (Path.cwd().resolve(), *Path.cwd().resolve().parents):
                raise FileExistsError(f"{self.path} is the working directory or holds it: "
                                      "--overwrite does not replace it; choose another --out")
            here = self.path.resolve()
            inside = [f"{key} ({p})" for key, p in (inputs or {}).items()
                      if here in Path(p).resolve().parents]
            if inside:
                raise ValueError(
                    f"{', '.join(inside)} {'lies' if len(inside) == 1 else 'lie'} inside the "
                    f"run directory {self.path} that --overwrite replaces: copy "
                    f"{'it' if len(inside) == 1 else 'them'} elsewhere first, or choose another "
                    "--out")
            # unique per call: an interrupted --overwrite leaves its aside folder (deleted by
            # the next commit), and a notebook may overwrite the same path again in one process
            self._old = self.path.with_name(
                f".{self.path.name}.replaced-{os.getpid()}-{uuid.uuid4().hex[:8]}")
            os.replace(self.path, self._old)
        self.path.mkdir(parents=True, exist_ok=True)
        self._staging = self.path / ".outputs-partial"

    @property
    def replaced(self) -> Path | None:
        """Where the directory this one replaces waits until :meth:`commit` (else ``None``)."""
        return self._old

    @property
    def staging(self) -> Path:
        """Hidden folder for the final outputs, created on first use."""
        self._staging.mkdir(exist_ok=True)
        return self._staging

    def file(self, name) -> Path:
        return self.staging / name

    def commit(self) -> Path:
        """Move the staged outputs in (each file atomically, ``run.json`` last)."""
        names = sorted(p.name for p in self.staging.iterdir())
        for name in names:  # every file on disk before any rename (a power loss: old or new)
            if (self.staging / name).is_file():
                fsync_file(self.staging / name)
        for name in [n for n in names if n != "run.json"] + [n for n in names if n == "run.json"]:
            os.replace(self.staging / name, self.path / name)
        fsync_dir(self.path)
        self.staging.rmdir()
        if self._old is not None:
            shutil.rmtree(self._old)
            self._old = None
        for p in self._stale:
            shutil.rmtree(p, ignore_errors=True)
        self._stale = []
        return self.path

    def rollback(self) -> None:
        """Undo the directory of a run that failed before it wrote anything to resume.

        Deletes what this run wrote and puts back what was there before: the replaced
        directory (``overwrite``), an empty directory, or nothing.  Not for resumed runs.
        """
        shutil.rmtree(self.path, ignore_errors=True)
        if self._old is not None:
            os.replace(self._old, self.path)
            self._old = None
        elif not self._created:
            self.path.mkdir(parents=True, exist_ok=True)


class RunResult(NamedTuple):
    """What :func:`bayesreg.run` returns.

    Attributes
    ----------
    dir : Path  the run directory
    posterior : DataTree  ArviZ posterior and sample stats
    summary : pandas.DataFrame
    errors : dict or None  error table (synthetic truth)
    info : dict  content of ``run.json``
    """

    dir: Path
    posterior: object
    summary: object
    errors: dict | None
    info: dict


def _atomic_text(path: Path, text: str):
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(text)
    replace_durably(tmp, path)


def _versions():
    out = {"python": platform.python_version()}
    for p in ("bayesreg", "jax", "jaxlib", "blackjax", "numpyro", "arviz", "numpy", "scipy",
              "pytetwild", "scikit-image", "nibabel", "nilearn", "meshio"):
        try:
            out[p] = metadata.version(p)
        except metadata.PackageNotFoundError:
            out[p] = None
    return out


def error_table(problem, result, u_init, u_mean=None) -> dict | None:
    """Error of the posterior mean against the synthetic truth, mm (``None`` without truth).

    Parameters
    ----------
    problem : bayesreg.pipeline.Problem
    result : bayesreg.sampler.SamplerResult
    u_init : (N, 3) ndarray
        Nodal displacement of the chains' central start (mm).
    u_mean : (N, 3) ndarray, optional
        The posterior mean nodal displacement, if already computed.

    Returns
    -------
    dict
        For the boundary nodes (paper Table 1 style) the median, 95th percentile and max of
        ``|E[u_b] - u_b_true|`` and of the initial configuration's error; the MSE over all
        nodes (mm^2); coverage of the true boundary displacement components by the central
        50/90/95% credible intervals; the lam/mu ratio posterior per group.
    """
    from bayesreg.diagnostics import coverage

    from bayesreg.posterior import elastic_groups

    mesh, truth = problem.mesh, problem.truth
    post = problem.posterior
    nb3 = 3 * post.n_boundary
    lam_g, mu_g = (np.asarray(a) for a in elastic_groups(post, result.positions[..., nb3:]))
    ratio = lam_g / mu_g
    ratios = {}
    for k, name in enumerate(problem.layout.group_names[:16]):
        r = ratio[..., k].ravel()
        ratios[name] = {
            "mean": float(r.mean()), "sd": float(r.std()),
            "q05": float(np.quantile(r, 0.05)), "q95": float(np.quantile(r, 0.95)),
        }
    if truth is None:
        return {"ratio": ratios}
    if problem.layout.group_names == ("csf", "gm", "wm"):
        true_ratio = truth.lam_e / truth.mu_e
        for k, name in enumerate(problem.layout.group_names):
            ratios[name]["true"] = float(np.median(true_ratio[mesh.tissue == k]))
    u_true_b = truth.u[mesh.boundary]
    mean_b = result.positions[..., :nb3].mean(axis=(0, 1)).reshape(post.n_boundary, 3)
    init_b = np.asarray(u_init)[mesh.boundary]

    def stats(err):
        return {"median": float(np.median(err)), "q95": float(np.quantile(err, 0.95)),
                "max": float(err.max())}

    if u_mean is None:
        u_mean = _nodal_mean(problem, result)
    return {
        "boundary_initial_mm": stats(np.linalg.norm(init_b - u_true_b, axis=1)),
        "boundary_posterior_mean_mm": stats(np.linalg.norm(mean_b - u_true_b, axis=1)),
        "all_nodes_posterior_mean_mm": stats(np.linalg.norm(u_mean - truth.u, axis=1)),
        "mse_all_nodes_mm2": float(np.mean(np.sum((u_mean - truth.u) ** 2, axis=1))),
        "mse_all_nodes_initial_mm2": float(np.mean(np.sum((u_init - truth.u) ** 2, axis=1))),
        "coverage_boundary": {str(k): float(v) for k, v in coverage(
            result.positions[..., :nb3], u_true_b.ravel()).items()},
        "ratio": ratios,
    }


_CHUNK = 2048  # draws per chunk of the nodal statistics (memory CHUNK x N x 3 doubles)
_SPREAD_MAX_BYTES = 1 << 30  # the nodal covariances' accumulators, all threads together


def _node_slots(problem):
    """Mesh node indices of the sampled boundary nodes and of the solved interior nodes, in
    the order of ``u_b`` and ``u_i`` (the inverse of ``posterior.perm``)."""
    post = problem.posterior
    perm = np.asarray(post.perm)  # full[:, j] = [u_b, u_i][:, perm[j]]
    node = np.empty_like(perm)
    node[perm] = np.arange(len(perm))
    return node[:post.n_boundary], node[post.n_boundary:]


def _nodal_draws(problem, result, rows):
    """Nodal displacement draws ``(S, N, 3)`` mm in mesh node order for ``rows`` (a slice or
    indices) of the pooled ``(C*D)`` draws: sampled boundary and solved interior nodes
    written straight to their places (no copy of all draws)."""
    b, i = _node_slots(problem)
    n_chains, n_draws = result.positions.shape[:2]
    chain, draw = np.divmod(np.arange(n_chains * n_draws)[rows], n_draws)
    pos, ui = result.positions[chain, draw], result.interior[chain, draw]
    out = np.empty((len(pos), len(b) + len(i), 3))
    out[:, b] = pos[:, : 3 * len(b)].reshape(len(pos), len(b), 3)
    out[:, i] = ui
    return out


def _chunks(result):
    n, chunk = result.positions.shape[0] * result.positions.shape[1], _CHUNK
    return [slice(a, min(a + chunk, n)) for a in range(0, n, chunk)]


def _nodal_mean(problem, result) -> np.ndarray:
    """Posterior mean nodal displacement ``(N, 3)`` mm: the means of the stored ``u_b`` and
    ``u_i`` draws put in mesh node order (no nodal draws assembled)."""
    b, i = _node_slots(problem)
    mean = np.empty((len(b) + len(i), 3))
    mean[b] = result.positions[..., : 3 * len(b)].mean(axis=(0, 1)).reshape(len(b), 3)
    mean[i] = result.interior.mean(axis=(0, 1))
    return mean


def _nodal_spread(problem, result, mean, *, block=128):
    """Per-node spread of the draws about ``mean``, over chunks of draws.

    Returns ``cov (3, N, N)`` (covariance per axis, mm^2), ``sd (N, 3)``, and the sd and
    inter-quartile range of ``|u|`` per node ``(N,)`` (mm).  Memory: the ``(C*D, N)``
    norms and one chunk, not the ``(C*D, N, 3)`` draws.
    """
    from concurrent.futures import ThreadPoolExecutor

    from bayesreg.sampler import _cores

    n_nodes = mean.shape[0]
    norm = np.empty((result.positions.shape[0] * result.positions.shape[1], n_nodes))

    def accumulate(rows):
        cov = np.zeros((3, n_nodes, n_nodes))
        for r in rows:
            x = _nodal_draws(problem, result, r)
            norm[r] = np.linalg.norm(x, axis=2)
            x -= mean
            for c in range(3):
                xc = np.ascontiguousarray(x[:, :, c])
                cov[c] += xc.T @ xc
        return cov

    # the chunks shared among threads (BLAS and NumPy release the GIL), one (3, N, N)
    # accumulator each, as many as fit in _SPREAD_MAX_BYTES (the 10k-node mesh: one)
    chunks = _chunks(result)
    workers = max(1, min(_cores(), len(chunks), _SPREAD_MAX_BYTES // (24 * n_nodes * n_nodes)))
    with ThreadPoolExecutor(workers) as pool:
        covs = list(pool.map(accumulate, [chunks[k::workers] for k in range(workers)]))
    cov = covs.pop(0)
    for other in covs:  # in place: no third (3, N, N) array
        cov += other
    cov /= len(norm)
    sd = np.sqrt(np.maximum(np.stack([np.diag(cov[c]) for c in range(3)], axis=1), 0.0))
    norm_sd, norm_iqr = np.empty(n_nodes), np.empty(n_nodes)
    for a in range(0, n_nodes, block):
        cols = norm[:, a:a + block]
        norm_sd[a:a + block] = cols.std(axis=0)
        q75, q25 = np.quantile(cols, [0.75, 0.25], axis=0)
        norm_iqr[a:a + block] = q75 - q25
    return cov, sd, norm_sd, norm_iqr


def _summary(tree, small: list, big: str, dim: str, *, parts: int | None = None):
    """``az.summary`` of the variables ``small + [big]`` (90% equal-tailed intervals), the
    rows of ``big`` computed in ``parts`` threads over contiguous blocks of its ``dim``.

    The same table as one ``az.summary(tree, var_names=small + [big], ...)`` call, row for
    row and value for value (ArviZ's diagnostics are per estimand; tested).  ArviZ's NumPy
    work (the rank normalisations' sorts above all) releases the GIL, so the threads use
    the cores: on the paper experiment's 3 x 25,000 draws of 1,032 boundary coordinates,
    60 s in one call against 24 s for ``u_b`` in two threads (2-core CPU).  ``parts``
    defaults to the cores available.
    """
    import arviz as az
    import pandas as pd

    from bayesreg.sampler import _cores

    def one(names, sel=None):
        t = tree if sel is None else tree.isel({dim: sel})
        return az.summary(t, var_names=names, ci_prob=0.9, ci_kind="eti")

    n = tree.posterior.sizes[dim]
    parts = max(1, min(parts or _cores(), n))
    bounds = np.linspace(0, n, parts + 1).astype(int)
    blocks = [slice(a, b) for a, b in zip(bounds[:-1], bounds[1:]) if b > a]
    if len(blocks) <= 1:
        return one(small + [big])
    from concurrent.futures import ThreadPoolExecutor

    with ThreadPoolExecutor(len(blocks)) as pool:
        futures = [pool.submit(one, [big], sel) for sel in blocks]
        head = one(small)
        return pd.concat([head] + [f.result() for f in futures])


def _per_solve(cg_per_step, cfg, block_names):
    """Mean CG iterations per solve from the per-step count, or ``None`` when a step's
    counted solves are not a fixed number.

    The random walk solves once per block and step (a proposal whose parameters leave the
    prior support is rejected without a solve and counts 0), except for the ``u_b`` block
    with the cached condensation (``u_i = H u_b``: no solve; the elastic block's solves are
    then all there are).  A gradient-kernel transition counts
    the solves outside its trajectory: with the cached condensation (the default) the
    trajectory needs none, and the elastic block makes ``elastic_moves`` solves plus one
    evaluation before them; without it every gradient solves (uncounted) and the interior
    after a moved trajectory is one more solve, so the count per step varies.
    """
    if not cfg.sampler.gradient:
        solving = [b for b in block_names if not (b == "u_b" and cfg.sampler.use_condensed)]
        return float(cg_per_step / len(solving))
    if not cfg.sampler.use_condensed or "elastic" not in block_names:
        return None
    return float(cg_per_step / (cfg.sampler.elastic_moves + 1))


def _adapted(cfg, result) -> dict:
    """The tuned values frozen after the warm-up (saved with the run)."""
    if cfg.sampler.gradient:
        step, inv_mass, eta_scale = (np.asarray(a) for a in result.sigma)
        return {"step_size_per_chain": step.tolist(),
                "inverse_mass_diag_quantiles_0_50_100": np.quantile(
                    inv_mass if inv_mass.ndim == 2 else np.diagonal(inv_mass, axis1=1, axis2=2),
                    [0, 0.5, 1]).tolist(),
                "elastic_proposal_sd_per_chain": _marginal_sd(eta_scale, eta_scale.ndim == 3).tolist(),
                "elastic_factor_per_chain": eta_scale.tolist()}
    sds = [_marginal_sd(np.asarray(s_), np.ndim(s_) == 2) for s_ in result.sigma]
    return {"proposal_sd_rms_per_block": [float(np.sqrt(np.mean(sd ** 2))) for sd in sds],
            "elastic_proposal_sd": sds[-1].tolist() if len(sds) > 1 else None}


def _marginal_sd(scale: np.ndarray, factor: bool) -> np.ndarray:
    """Marginal proposal standard deviations ``(..., d)`` of independent scales ``(..., d)``
    or of lower-triangular factors ``L`` ``(..., d, d)`` (``sqrt(diag(L L^T))``)."""
    return np.sqrt(np.sum(scale ** 2, axis=-1)) if factor else np.abs(scale)


def format_report(errors: dict | None, info: dict) -> str:
    """The short table the run prints (error vs truth, ratio posteriors, sampler figures)."""
    lines = []
    mesh = info.get("mesh") or {}
    if "n_nodes" in mesh:
        line = (f"mesh {mesh['n_nodes']} nodes ({mesh.get('n_boundary_nodes', '?')} boundary), "
                f"{mesh.get('n_tets', '?')} tets")
        meshing = mesh.get("meshing") or {}
        if meshing.get("target_nodes"):
            line += (f"; target {meshing['target_nodes']} within {meshing['tolerance']:.0%}: "
                     f"{'met' if meshing['within_tolerance'] else 'NOT met (closest kept)'} in "
                     f"{len(meshing['attempts'])} attempt(s), edge {meshing['edge_length_mm']:.3g} mm")
        if meshing.get("file"):
            line += f"; read from {meshing['file']}"
        lines.append(line)
    s = info["sampler"]
    acc = ", ".join(f"{b} {a:.3f}" for b, a in zip(s["blocks"], s["acceptance"]))
    lines.append(
        f"draws/chain {s['draws_per_chain']} (thinning {s['thinning']})  chains {s['chains']}  "
        f"acceptance {acc}"
    )
    lines.append(
        f"R-hat max: classic {s['rhat_classic_max']:.3f}, split {s['rhat_classic_split_max']:.3f} "
        f"(stop below {s['rhat_threshold']} on {'split' if s['rhat_split_monitored'] else 'classic'}), "
        f"rank-normalised {s['rhat_rank_max']:.3f}  ESS bulk min {s['ess_bulk_min']:.0f}"
    )
    per_solve = s.get("cg_iterations_per_solve_mean")
    cg = (f"CG iterations/solve mean {per_solve:.1f}" if per_solve is not None else
          f"CG iterations/step mean {s['cg_iterations_per_step_mean']:.1f} (outside the trajectories)")
    if s.get("cg_preconditioner"):
        cg += f" ({s['cg_preconditioner']} preconditioner)"
    lines.append(f"{cg}  failed solves {s['solve_failures']}  steps/s per chain {s['steps_per_s_per_chain']:.1f}")
    if s.get("kind", "rwmh") != "rwmh":
        lines.append(f"{s['kind']}: gradients/step {s['gradient_evaluations_per_step_mean']:.1f}  "
                     f"divergences {s['divergences']}  prior normaliser {s['prior_normaliser']}")
    if errors and "boundary_posterior_mean_mm" in errors:
        lines.append("error vs truth (mm)           median    95th     max")
        for key, label in (("boundary_initial_mm", "boundary, initial"),
                           ("boundary_posterior_mean_mm", "boundary, posterior mean"),
                           ("all_nodes_posterior_mean_mm", "all nodes, posterior mean")):
            e = errors[key]
            lines.append(f"  {label:<27} {e['median']:7.3f} {e['q95']:7.3f} {e['max']:7.3f}")
        lines.append(f"  MSE all nodes {errors['mse_all_nodes_mm2']:.4f} mm^2")
    if errors:
        lines.append("lam/mu posterior        mean      sd     5%     95%   truth")
        for name, r in errors["ratio"].items():
            tr = f"{r['true']:7.3g}" if "true" in r else "      -"
            lines.append(f"  {name:<14} {r['mean']:9.3f} {r['sd']:7.3f} {r['q05']:7.3f} {r['q95']:7.3f} {tr}")
    return "\n".join(lines)


def _plots(run_dir: RunDirectory, tree, names, truth_ratio):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ratio = np.asarray(tree.posterior["ratio"].values)  # (C, D, G)
    n = min(ratio.shape[-1], 6)
    fig, axes = plt.subplots(n, 2, figsize=(10, 2.2 * n), squeeze=False)
    for k in range(n):
        for c in range(ratio.shape[0]):
            axes[k, 0].plot(ratio[c, :, k], lw=0.6, label=f"chain {c}")
            axes[k, 1].hist(ratio[c, :, k], bins=40, histtype="step", density=True)
        axes[k, 0].set_ylabel(f"lam/mu {names[k]}")
        if truth_ratio is not None:
            axes[k, 0].axhline(truth_ratio[k], color="k", ls="--", lw=1)
            axes[k, 1].axvline(truth_ratio[k], color="k", ls="--", lw=1, label="truth")
    axes[0, 0].legend(fontsize=7)
    axes[-1, 0].set_xlabel("draw (thinned)")
    axes[-1, 1].set_xlabel("lam/mu")
    fig.tight_layout()
    fig.savefig(run_dir.file("trace.png"), dpi=90)
    plt.close(fig)

    ub = np.asarray(tree.posterior["u_b"].values)  # (C, D, nb, 3)
    sd = ub.reshape(-1, ub.shape[2], 3).std(0).sum(1)
    node = int(np.argmax(sd))
    fig, axes = plt.subplots(1, 3, figsize=(11, 3))
    for a, ax in enumerate(axes):
        for c in range(ub.shape[0]):
            ax.hist(ub[c, :, node, a], bins=40, histtype="step", density=True)
        ax.set_xlabel(f"u_{'xyz'[a]} (mm), boundary node {int(tree.posterior['node'][node])}")
    fig.suptitle("marginal posterior of the most uncertain boundary node")
    fig.tight_layout()
    fig.savefig(run_dir.file("marginals.png"), dpi=90)
    plt.close(fig)


_VOXEL_DRAWS = 400  # evenly spaced draws behind the voxel-wise spread of |u|


def _voxel_norm_spread(w, draws, max_draws=_VOXEL_DRAWS, block=8192):
    """Per-voxel sd and inter-quartile range of ``|u|`` from FE-interpolated draws.

    ``w`` is the ``(P, N)`` interpolation matrix, ``draws`` ``(S, N, 3)``; at most
    ``max_draws`` evenly spaced draws are used, voxels in blocks (memory ``block x S x 3``).
    Returns two ``(P,)`` arrays, mm.
    """
    step = max(1, len(draws) // max_draws)
    d = np.asarray(draws[::step], np.float64)
    flat = d.transpose(1, 0, 2).reshape(d.shape[1], -1)  # (N, S*3)
    sd = np.zeros(w.shape[0])
    iqr = np.zeros(w.shape[0])
    rows = np.flatnonzero(np.diff(w.indptr) > 0)
    for a in range(0, len(rows), block):
        r = rows[a:a + block]
        vals = (w[r] @ flat).reshape(len(r), len(d), 3)
        norm = np.linalg.norm(vals, axis=2)
        sd[r] = norm.std(axis=1)
        q75, q25 = np.quantile(norm, [0.75, 0.25], axis=1)
        iqr[r] = q75 - q25
    return sd, iqr


def _overlay(run_dir: RunDirectory, f: Image, iqr, labels: Image):
    """``uncertainty.png``: IQR of ``|u|`` over ``f`` on three orthogonal slices."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    brain = np.isin(labels.data, (1, 2, 3))
    c = np.round(np.argwhere(brain).mean(0)).astype(int) if brain.any() else np.array(f.data.shape) // 2
    vmax = float(np.quantile(iqr[brain], 0.99)) if brain.any() and iqr[brain].max() > 0 else None
    fig, axes = plt.subplots(1, 3, figsize=(12, 4))
    for ax, axis, name in zip(axes, range(3), ("sagittal", "coronal", "axial")):
        sl = [slice(None)] * 3
        sl[axis] = c[axis]
        img = np.asarray(f.data)[tuple(sl)].T
        unc = np.ma.masked_where(~brain[tuple(sl)].T, iqr[tuple(sl)].T)
        ax.imshow(img, cmap="gray", origin="lower")
        im = ax.imshow(unc, cmap="magma", alpha=0.7, origin="lower", vmin=0, vmax=vmax)
        ax.set_title(f"{name} slice {c[axis]}")
        ax.axis("off")
    fig.colorbar(im, ax=axes, shrink=0.8, label="IQR of |u| (mm)")
    fig.suptitle("posterior uncertainty of the displacement magnitude over f")
    fig.savefig(run_dir.file("uncertainty.png"), dpi=90)
    plt.close(fig)


def write_outputs(run_dir: RunDirectory, cfg, problem, result, init, timings, init_info=None, *,
                  resumed=False) -> RunResult:
    """Write every output of a run (see module docstring) and commit the directory.

    ``init`` is the run's :class:`bayesreg.pipeline.Initialisation` (its central start is
    the "initial configuration" of the error table).
    """
    import meshio

    from bayesreg.diagnostics import arviz_fast_ess, gelman_rubin, to_datatree
    from bayesreg.mesh import mesh_quality
    from bayesreg.pipeline import cg_preconditioner
    from bayesreg.posterior import elastic_groups, solve_position
    from bayesreg.synthetic import grid_moments_from, interpolation_matrix, locate_grid

    post, mesh, layout = problem.posterior, problem.mesh, problem.layout
    nb = post.n_boundary
    pos = result.positions
    c, d = pos.shape[:2]
    ub = pos[..., : 3 * nb].reshape(c, d, nb, 3)
    lam_g, mu_g = (np.asarray(a) for a in elastic_groups(post, pos[..., 3 * nb:]))
    names = list(layout.group_names)
    if result.acceptance.shape[-1] == 2:
        block_names = ["u_b", "elastic"]
    else:
        block_names = ["u_b"] if cfg.sampler.gradient else ["joint"]
    tree = to_datatree(
        {"u_b": ub, "lam": lam_g, "mu": mu_g, "ratio": lam_g / mu_g},
        sample_stats={
            "acceptance_rate": result.acceptance,
            "lp": result.logdensity,
            "cg_iterations": result.cg_iterations,
            "solve_failures": result.solve_failures,
            "n_grad": result.grad_evals,
            "diverging": result.divergences,
        },
        dims={"u_b": ["node", "axis"], "lam": ["group"], "mu": ["group"], "ratio": ["group"],
              "acceptance_rate": ["block"]},
        coords={"node": mesh.boundary.astype(int), "axis": ["x", "y", "z"], "group": names,
                "block": block_names},
        attrs={"units_u_b": "mm (world)", "name": cfg.name},
    )
    tree.to_netcdf(run_dir.file("posterior.nc"))

    var_names = ["lam", "mu", "ratio", "u_b"]
    with warnings.catch_warnings():  # fixed parameters have zero variance: NaN R-hat
        warnings.simplefilter("ignore", RuntimeWarning)
        with arviz_fast_ess():  # ArviZ's numbers, without its Python loop over lags
            summary = _summary(tree, ["lam", "mu", "ratio"], "u_b", "node")
        classic, split = [], []
        for v in var_names:
            x = np.asarray(tree.posterior[v].values)
            classic.append(gelman_rubin(x.reshape(c, d, -1)))
            split.append(gelman_rubin(x.reshape(c, d, -1), split=True))
    summary["rhat_classic"] = np.concatenate(classic)
    summary["rhat_classic_split"] = np.concatenate(split)
    fixed_rows = [f"{p}[{names[g]}]" for p, g, _ in layout.fixed]
    summary = summary.drop(index=[r for r in fixed_rows if r in summary.index])
    tmp = run_dir.file("summary.csv.tmp")
    summary.to_csv(tmp)
    os.replace(tmp, run_dir.file("summary.csv"))

    # displacement maps: on the mesh and on the image grid (FE interpolation)
    # the nodal statistics over chunks of draws: never all (C*D, N, 3) draws at once
    u_mean = _nodal_mean(problem, result)
    cov, u_sd, norm_sd_n, norm_iqr_n = _nodal_spread(problem, result, u_mean)
    u_init = np.asarray(solve_position(post, init.center, rtol=cfg.solver.rtol,
                                       maxiter=cfg.solver.maxiter)[0])
    point_data = {"u_mean": u_mean, "u_sd": u_sd, "u_norm_sd": norm_sd_n,
                  "u_norm_iqr": norm_iqr_n, "u_init": u_init}
    if problem.truth is not None:
        point_data["u_true"] = problem.truth.u
        point_data["u_error"] = u_mean - problem.truth.u
    meshio.write(
        run_dir.file("mesh.vtu"),
        meshio.Mesh(mesh.nodes, [("tetra", mesh.tets)], point_data=point_data,
                    cell_data={"tissue": [mesh.tissue.astype(np.int32)]}),
    )
    located = locate_grid(mesh, problem.f)
    w, in_mesh = interpolation_matrix(mesh, problem.f, located=located)
    grid = problem.f.data.shape[:3]
    mean_img, sd_img = grid_moments_from(mesh, problem.f, u_mean, cov, located=located)
    del cov
    n_draws = c * d
    norm_sd, norm_iqr = _voxel_norm_spread(
        w, _nodal_draws(problem, result, slice(None, None, max(1, n_draws // _VOXEL_DRAWS))))
    aff = problem.f.affine
    vol = {"displacement_mean": mean_img, "displacement_sd": sd_img,
           "displacement_norm_sd": norm_sd.reshape(grid), "displacement_norm_iqr": norm_iqr.reshape(grid),
           "displacement_init": (w @ u_init).reshape(*grid, 3)}
    if problem.truth is not None:
        vol["displacement_true"] = (w @ problem.truth.u).reshape(*grid, 3)
    for name, arr in vol.items():
        save_nifti(Image(arr.astype(np.float32), aff), run_dir.file(f"{name}.nii.gz"))
    save_nifti(Image(in_mesh.astype(np.uint8), aff), run_dir.file("mesh_mask.nii.gz"))
    _overlay(run_dir, problem.f, norm_iqr.reshape(grid), problem.labels)
    save_nifti(Image(problem.f.data.astype(np.float32), aff), run_dir.file("f.nii.gz"))
    save_nifti(Image(np.asarray(problem.m.data, np.float32), problem.m.affine), run_dir.file("m.nii.gz"))
    save_nifti(problem.labels, run_dir.file("labels.nii.gz"))

    errors = error_table(problem, result, u_init, u_mean)
    truth_ratio = None
    if errors and all("true" in errors["ratio"].get(nm, {}) for nm in names[:6]):
        truth_ratio = [errors["ratio"][nm]["true"] for nm in names[:6]]
    _plots(run_dir, tree, names, truth_ratio)

    rank_rhat = summary["r_hat"].to_numpy(dtype=float)
    info = {
        "name": cfg.name,
        "seed": cfg.seed,
        "config": cfg.model_dump(mode="json"),
        "versions": _versions(),
        "timings_s": {k: round(float(v), 3) for k, v in timings.items()},
        "mesh": {**mesh_quality(mesh), **({"meshing": problem.mesh_info} if problem.mesh_info else {})},
        "intensity_scale": problem.intensity_scale,
        "parameters": {"free": layout.free_names,
                       "fixed": [f"{p}_{names[g]}={v}" for p, g, v in layout.fixed]},
        "sampler": {
            "kind": cfg.sampler.kind,
            "prior_normaliser": cfg.model.prior_normaliser,
            "condensed": cfg.sampler.use_condensed,
            "cg_preconditioner": cg_preconditioner(problem, cfg),
            "gradient_evaluations_per_step_mean": float(result.grad_evals.mean()),
            "divergences": int(result.divergences.sum()),
            "adapted": _adapted(cfg, result),
            "proposal": cfg.sampler.proposal,
            "chains": int(c),
            "draws_per_chain": int(d),
            "thinning": cfg.sampler.thinning,
            "steps_per_chain": int(d * cfg.sampler.thinning + cfg.sampler.warmup_steps),
            "blocks": block_names,
            "acceptance": [float(a) for a in result.acceptance.reshape(-1, len(block_names)).mean(0)],
            # None without a warm-up (the paper's fixed kernel), not NaN (not JSON)
            "warmup_acceptance": ([float(a) for a in result.warmup_acceptance]
                                  if np.all(np.isfinite(result.warmup_acceptance)) else None),
            "rhat_classic_max": float(summary["rhat_classic"].max()),
            "rhat_classic_split_max": float(summary["rhat_classic_split"].max()),
            "rhat_split_monitored": cfg.sampler.rhat_split,
            "rhat_rank_max": float(np.nanmax(rank_rhat)),
            "ess_bulk_min": float(summary["ess_bulk"].min()),
            "converged": bool(result.converged),
            "rhat_threshold": cfg.sampler.rhat_threshold,
            "rhat_history": [[int(a), float(b)] for a, b in result.rhat_history],
            "cg_iterations_per_step_mean": float(result.cg_iterations.mean()),
            "cg_iterations_per_solve_mean": _per_solve(result.cg_iterations.mean(), cfg, block_names),
            "solve_failures": int(result.solve_failures.sum()),
            "steps_per_s_per_chain": float(d * cfg.sampler.thinning / max(timings.get("sampling_s", 1e-9), 1e-9)),
        },
        "init": init_info or {},
        "truth": problem.truth_info,
        "resumed": bool(resumed),
        "n_skull_voxels_carved": problem.n_skull_carved,
        "errors": errors,
    }
    _atomic_text(run_dir.file("errors.json"), json.dumps(errors, indent=2))
    _atomic_text(run_dir.file("run.json"), json.dumps(info, indent=2))
    path = run_dir.commit()
    return RunResult(path, tree, summary, errors, info)

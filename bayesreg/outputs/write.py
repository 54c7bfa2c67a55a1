"""The outputs of a finished run: ArviZ posterior, summaries, displacement maps, ``run.json``.

Files of one run (all written atomically into its :class:`~bayesreg.rundir.RunDirectory`; a
run in progress keeps its draws in ``checkpoint/``, see :mod:`bayesreg.checkpoint`):

==================================  ======================================================
``posterior.nc``                    ArviZ DataTree (NetCDF): ``u_b`` (chain, draw, node, axis)
                                    mm, ``lam``, ``mu``, ``ratio = lam/mu`` (chain, draw,
                                    group); sample stats ``acceptance_rate``, ``lp``,
                                    ``cg_iterations``, ``solve_failures``
``summary.csv``                     mean, sd, 90% central credible interval (``eti90_lb``,
                                    ``eti90_ub``), ESS, rank R-hat (ArviZ), classic R-hat
``displacement_mean.nii.gz``        posterior mean of ``u`` on the image grid as an ITK/ANTs
                                    displacement field (:mod:`bayesreg.interop.transforms`: 5-D
                                    (I, J, K, 1, 3), intent VECTOR, LPS mm, fixed to moving)
``displacement_sd.nii.gz``          posterior sd of each RAS component of ``u``, (I, J, K, 3) mm
``displacement_norm_sd.nii.gz``     posterior sd of ``|u|``, (I, J, K) mm
``displacement_norm_iqr.nii.gz``    posterior inter-quartile range of ``|u|``, (I, J, K) mm
``displacement_init.nii.gz``        the chains' central start (ITK/ANTs field)
``displacement_true.nii.gz``        the synthetic truth (synthetic runs; ITK/ANTs field)
``displacement_reference.nii.gz``   the point estimate to beat: scikit-image optical flow
                                    of ``f`` to ``m`` (synthetic runs; ITK/ANTs field)
``mesh_mask.nii.gz``                voxels inside the undeformed mesh (where the maps are defined)
``discrepancy_amplitude.nii.gz``    ``model.discrepancy`` (not none): ``|E[d]|`` of the model
                                    discrepancy, (I, J, K) mm, and ``discrepancy.png`` over ``f``
                                    (``posterior.nc`` then holds ``d`` and ``discrepancy_rms``)
``mesh.vtu``                        mesh with point data ``u_mean``, ``u_sd``, ``u_norm_sd``,
                                    ``u_norm_iqr``, ``u_init``, ``u_true``, ``u_error``
                                    (``d_mean`` with a model discrepancy); cell
                                    data ``label``: the element's tissue in the label map's
                                    coding (1 CSF, 2 GM, 3 WM); world RAS mm (``bayesreg export --format slicer``
                                    writes it in LPS for 3D Slicer)
``f.nii.gz``, ``m.nii.gz``, ``labels.nii.gz``  the (scaled) images and label map used
``trace.png``, ``marginals.png``    trace and marginal plots of the elastic parameters
``uncertainty.png``                 IQR of ``|u|`` over ``f`` on three orthogonal slices
``errors.json``                     error of the posterior mean and of the start against the
                                    truth, coverage of the credible intervals (synthetic)
``run.json``                        resolved config, seed, versions, timings, acceptance, CG,
                                    R-hat, how the truth and the starts were made
``checkpoint/``                     config, problem (images, mesh, truth), starts; while the
                                    run goes also the draws so far and the sampler state
==================================  ======================================================

Maps on the image grid are the FE interpolation of the nodal values (zero outside the mesh).
"""

from __future__ import annotations

import platform
import time
import warnings
from concurrent.futures import ThreadPoolExecutor
from importlib import metadata

import meshio
import numpy as np

from bayesreg._files import dumps_json, write_text_atomic
from bayesreg.sampling.chains import available_cores
from bayesreg.config import Config
from bayesreg.sampling.convergence import gelman_rubin
from bayesreg.sampling.diagnostics import arviz_fast_ess, contraction, coverage, sampler_health, to_datatree
from bayesreg.outputs.fields import (
    VOXEL_DRAWS, discrepancy_summary, mesh_best_fit, nodal_draws, nodal_mean, nodal_spread,
    voxel_norm_spread)
from bayesreg.data.images import Image, save_nifti
from bayesreg.inference.initialisation import Initialisation, registration_field
from bayesreg.data.labels import TISSUE_LABELS, tissue_label
from bayesreg.mesh.tetmesh import boundary_nodes, mesh_quality
from bayesreg.outputs.plots import plot_brain_map, plot_parameters, plot_uncertainty
from bayesreg.outputs.result import RunResult
from bayesreg.outputs.printed import verdict
from bayesreg.model.posterior import (discrepancy_of, elastic_groups, similarity_log_likelihood,
                                      solve_position)
from bayesreg.model.problem import Problem, at_start
from bayesreg.rundir import RunDirectory
from bayesreg.sampling.driver import SamplerResult
from bayesreg.data.registration import displacement_at
from bayesreg.interop.transforms import FIXED_TO_MOVING, save_displacement
from bayesreg.mesh.warp import grid_moments_from, interpolation_matrix, locate_grid

__all__ = ["write_outputs", "error_table", "summary_table", "REFERENCE_NAMES"]


def _versions():
    out = {"python": platform.python_version()}
    for p in ("bayesreg", "jax", "jaxlib", "blackjax", "numpyro", "arviz", "numpy", "scipy",
              "pytetwild", "scikit-image", "nibabel", "nilearn", "meshio", "sparsax"):
        try:
            out[p] = metadata.version(p)
        except metadata.PackageNotFoundError:
            out[p] = None
    return out


MOVING_MM = 1.0  # "where tissue moves": nodes the truth moves at least this far, mm


def thinned_nodal_draws(problem, result) -> np.ndarray:
    """At most about ``VOXEL_DRAWS`` evenly spaced nodal draws ``(S, N, 3)`` mm of the pooled
    chains (:func:`bayesreg.outputs.fields.nodal_draws`)."""
    n_draws = result.positions.shape[0] * result.positions.shape[1]
    return nodal_draws(problem, result, slice(None, None, max(1, n_draws // VOXEL_DRAWS)))


def error_table(problem, result, u_init, u_mean=None, *, grid=None, reference=None,
                draws=None) -> dict | None:
    """Error of the posterior mean against the synthetic truth, mm (``None`` without truth).

    Parameters
    ----------
    problem : bayesreg.model.problem.Problem
    result : bayesreg.sampling.driver.SamplerResult
    u_init : (N, 3) ndarray
        Nodal displacement of the chains' central start (mm).
    u_mean : (N, 3) ndarray, optional
        The posterior mean nodal displacement, if already computed.
    grid : (w, in_mesh), optional
        The FE interpolation matrix ``(V, N)`` onto ``f``'s grid and its ``(V,)`` mask of
        voxels inside the mesh (or the grid's shape; :func:`bayesreg.mesh.warp.interpolation_matrix`): adds the errors
        over the brain's voxels.
    reference : Image, optional
        A point-estimate registration's dense field ``(I, J, K, 3)`` mm on ``f``'s grid
        (the run's TV-L1, :func:`bayesreg.inference.initialisation.registration_field`), compared
        beside the posterior mean.
    draws : (S, N, 3) ndarray, optional
        The thinned nodal draws of :func:`thinned_nodal_draws`, if already computed.

    Returns
    -------
    dict
        For the boundary nodes (paper Table 1 style) the median, 95th percentile and max of
        ``|E[u_b] - u_b_true|`` and of the initial configuration's error; the MSE over all
        nodes (mm^2); coverage of the true boundary displacement components by the central
        50/90/95% credible intervals, and of every node's components where the truth moves
        the node at least ``MOVING_MM`` (``coverage_moving``); the lam/mu ratio posterior per
        group (with its truth for an FE truth).  With ``grid``, ``brain``: over the voxels of
        CSF, GM and WM inside the mesh, the MSE (mm^2) and 95th percentile (mm) of the error
        of the posterior mean, the start and the reference (the truth there: the dense
        field of a truth the model did not make, else the FE interpolation of ``u``).  With
        ``reference``, ``boundary_reference_mm``: its error at the boundary nodes.  With
        ``grid`` and a dense truth, ``mesh_best_fit``: the mesh's resolution limit
        (:func:`bayesreg.outputs.fields.mesh_best_fit` over the brain's voxels), its
        distance from the truth at the nodes (mm), its brain MSE (mm^2) and the coverage of
        its components where the truth moves (the posterior can at best centre on it).
        ``image_fit``: :func:`image_fit` of the truth's and the posterior mean's ``u``.
    """
    mesh, truth = problem.mesh, problem.truth
    post = problem.posterior
    lam_g, mu_g = (np.asarray(a) for a in elastic_groups(post, result.positions[..., post.n_displacement:]))
    ratio = lam_g / mu_g
    ratios = {}
    for k, name in enumerate(problem.layout.group_names[:16]):
        r = ratio[..., k].ravel()
        ratios[name] = {
            "mean": float(r.mean()), "sd": float(r.std()), "median": float(np.median(r)),
            "q05": float(np.quantile(r, 0.05)), "q95": float(np.quantile(r, 0.95)),
        }
    if truth is None:
        return {"ratio": ratios}
    if problem.layout.group_names == ("csf", "gm", "wm") and truth.parameters_known:
        true_ratio = truth.lam_e / truth.mu_e
        for k, name in enumerate(problem.layout.group_names):
            ratios[name]["true"] = float(np.median(true_ratio[mesh.tissue == k]))
    # the surface nodes (the sampled ones, unless every node is: model.interior: sample)
    surface = boundary_nodes(mesh.tets)
    slot = np.full(len(mesh.nodes), -1)
    slot[np.asarray(mesh.boundary)] = np.arange(post.n_boundary)
    cols = (3 * slot[surface][:, None] + np.arange(3)).ravel()
    u_true_b = truth.u[surface]
    mean_b = result.positions[..., cols].mean(axis=(0, 1)).reshape(len(surface), 3)
    init_b = np.asarray(u_init)[surface]

    def stats(err):
        return {"median": float(np.median(err)), "q95": float(np.quantile(err, 0.95)),
                "max": float(err.max())}

    if u_mean is None:
        u_mean = nodal_mean(problem, result)
    # every node's components where the truth moves the node: thinned nodal draws
    moving = np.linalg.norm(truth.u, axis=1) >= MOVING_MM
    cov_moving = None
    if moving.any():
        draws = thinned_nodal_draws(problem, result) if draws is None else draws
        cov_moving = {str(k): float(v) for k, v in coverage(
            draws[:, moving].reshape(len(draws), -1), truth.u[moving].ravel()).items()}
        cov_moving["n_components"] = int(3 * moving.sum())
    out = {
        "boundary_initial_mm": stats(np.linalg.norm(init_b - u_true_b, axis=1)),
        "boundary_posterior_mean_mm": stats(np.linalg.norm(mean_b - u_true_b, axis=1)),
        "all_nodes_posterior_mean_mm": stats(np.linalg.norm(u_mean - truth.u, axis=1)),
        "mse_all_nodes_mm2": float(np.mean(np.sum((u_mean - truth.u) ** 2, axis=1))),
        "mse_all_nodes_initial_mm2": float(np.mean(np.sum((u_init - truth.u) ** 2, axis=1))),
        "coverage_boundary": {str(k): float(v) for k, v in coverage(
            result.positions[..., cols], u_true_b.ravel()).items()},
        "moving_threshold_mm": MOVING_MM,
        "coverage_moving": cov_moving,
        "truth_made_by_model": bool(truth.made_by_model),
        "ratio": ratios,
        "image_fit": image_fit(post, truth.u, u_mean),
    }
    if reference is not None:
        ref_b = displacement_at(reference, mesh.nodes[surface])
        out["boundary_reference_mm"] = stats(np.linalg.norm(ref_b - u_true_b, axis=1))
    if grid is not None:
        w, in_mesh = grid
        brain = np.isin(np.asarray(problem.labels.data).ravel(), TISSUE_LABELS) & np.ravel(in_mesh)
        w_brain = w[np.flatnonzero(brain)]  # the interpolation at the brain's voxels only
        true_v = (truth.field.data.reshape(-1, 3)[brain] if truth.field is not None
                  else w_brain @ truth.u)
        fields = {"posterior_mean": w_brain @ u_mean, "start": w_brain @ np.asarray(u_init)}
        if reference is not None:
            fields["reference"] = np.asarray(reference.data).reshape(-1, 3)[brain]
        err = {k: np.linalg.norm(v - true_v, axis=1) for k, v in fields.items()}
        out["brain"] = {"n_voxels": int(brain.sum()),
                        "mse_mm2": {k: float(np.mean(e**2)) for k, e in err.items()},
                        "q95_mm": {k: float(np.quantile(e, 0.95)) for k, e in err.items()}}
        if truth.field is not None:  # the mesh's resolution limit, and coverage against it
            fit = mesh_best_fit(w_brain, true_v, truth.u)
            best = {"nodes_from_truth_mm": stats(np.linalg.norm(fit - truth.u, axis=1)),
                    "brain_mse_mm2": float(np.mean(np.sum((w_brain @ fit - true_v) ** 2, axis=1)))}
            if moving.any():
                best["coverage_moving"] = {str(k): float(v) for k, v in coverage(
                    draws[:, moving].reshape(len(draws), -1), fit[moving].ravel()).items()}
            out["mesh_best_fit"] = best
    return out


def image_fit(post, u_true, u_mean) -> dict:
    """The images' term of ``log p`` (``-E_s / T_s`` in nats, paper Eqs. 1, 9; the marginal
    form with ``model.t_s_prior``) at the truth's nodal displacement ``u_true`` and at the
    posterior mean's ``u_mean`` (both ``(N, 3)`` mm), and ``gain_nats``, the second less the
    first.  Noise-free synthetic images fit the truth best but for their residual there
    (``f(x_q) - m(x_q + u(x_q))``: ``m`` re-interpolated, ``benchmarks/residual.py``) and,
    for a truth the model did not make, the mesh's; a positive gain is what the posterior
    fitted of it with the displacement and the parameters.  (Noisy images: the posterior
    fits part of the noise too, some nats per free direction.)"""
    import jax.numpy as jnp

    term = [float(similarity_log_likelihood(post, post.similarity.energy(jnp.asarray(u)[post.tets])))
            for u in (u_true, u_mean)]
    return {"truth": term[0], "posterior_mean": term[1], "gain_nats": term[1] - term[0]}


def summary_table(tree, small: list, big: str, dim: str, *, parts: int | None = None):
    """``az.summary`` of the variables ``small + [big]`` (90% equal-tailed intervals) with the
    Monte Carlo standard errors of the interval ends (``mcse_eti90_lb``, ``mcse_eti90_ub``:
    ``az.mcse(method="quantile")`` of the 5% and 95% quantiles), the rows of ``big`` computed
    in ``parts`` threads over contiguous blocks of its ``dim``.  ``ess_tail`` is that of the
    5% and 95% quantiles, the stop rule's (:func:`bayesreg.sampling.convergence.rank_figures`).

    The same table as one ``az.summary(tree, var_names=small + [big], ...)`` call, row for
    row and value for value (ArviZ's diagnostics are per estimand; tested).  ArviZ's NumPy
    work (the rank normalisations' sorts above all) releases the GIL, so the threads use
    the cores.  ``parts`` defaults to the cores available.
    """
    import arviz as az
    import pandas as pd

    def one(names, sel=None):
        t = tree if sel is None else tree.isel({dim: sel})
        table = az.summary(t, var_names=names, ci_prob=0.9, ci_kind="eti")

        def column(x):  # one value per row, in the table's order (C order over each variable)
            return np.concatenate([np.ravel(x[n].values) for n in names])

        # the tail ESS of the 5% and 95% quantiles (Vehtari et al. 2021; the stop rule's):
        # az.summary's own takes its quantiles from rcParams["stats.ci_prob"] (11% and 89%)
        table["ess_tail"] = column(az.ess(t, var_names=names, method="tail", prob=(0.05, 0.95)))
        for col, prob in (("mcse_eti90_lb", 0.05), ("mcse_eti90_ub", 0.95)):
            table[col] = column(az.mcse(t, var_names=names, method="quantile", prob=prob))
        return table

    n = tree.posterior.sizes[dim]
    parts = max(1, min(parts or available_cores(), n))
    bounds = np.linspace(0, n, parts + 1).astype(int)
    blocks = [slice(a, b) for a, b in zip(bounds[:-1], bounds[1:]) if b > a]
    if len(blocks) <= 1:
        return one(small + [big])
    with ThreadPoolExecutor(len(blocks)) as pool:
        futures = [pool.submit(one, [big], sel) for sel in blocks]
        head = one(small)
        return pd.concat([head] + [f.result() for f in futures])


#: What ``errors.json["reference"]`` names for each ``output.reference``.
REFERENCE_NAMES = {"tvl1": "skimage.registration.optical_flow_tvl1",
                   "ilk": "skimage.registration.optical_flow_ilk",
                   "syn": "ants.registration (SyN, bayesreg.interop.syn.SYN_DEFAULTS)"}


def write_outputs(run_dir: RunDirectory, cfg: Config, problem: Problem, result: SamplerResult,
                  init: Initialisation, timings: dict, init_info: dict | None = None, *,
                  resumed: bool = False, reference=None) -> RunResult:
    """Write every output of a run (see module docstring) and commit the directory.

    Parameters
    ----------
    run_dir : RunDirectory
    cfg : Config
        The run's resolved config (recorded in ``run.json``; the solver's tolerance solves
        the central start's interior).
    problem : Problem
    result : SamplerResult
        The draws and the sampler's own description of the run (:class:`bayesreg.sampling.driver.SamplerInfo`).
    init : Initialisation
        Its central start is the "initial configuration" of the error table.
    timings : dict
        Seconds of each stage.
    init_info : dict, optional
        How the starts were made (``run.json["init"]``).
    resumed : bool
        The run was resumed from a checkpoint.
    reference : Image, optional
        The :func:`~bayesreg.inference.initialisation.registration_field` of ``init.registration``
        if already computed (a registration start's): the reference when ``output.reference``
        names the same method; made here otherwise (synthetic runs with ``output.reference``
        other than ``none``).

    Returns
    -------
    RunResult
    """
    problem = at_start(problem, cfg, init)  # the posterior the chains sampled
    post, mesh, layout = problem.posterior, problem.mesh, problem.layout
    s_info = result.info
    nb = post.n_boundary
    pos = result.positions
    c, d = pos.shape[:2]
    ub = pos[..., : 3 * nb].reshape(c, d, nb, 3)
    phi = pos[..., post.n_displacement:]
    lam_g, mu_g = (np.asarray(a) for a in elastic_groups(post, phi))
    names = list(layout.group_names)
    block_names = list(s_info.blocks)
    posterior = {"u_b": ub, "ratio": lam_g / mu_g}
    dims = {"u_b": ["node", "axis"], "ratio": ["group"], "block_acceptance_rate": ["block"]}
    coords = {"node": mesh.boundary.astype(int), "axis": ["x", "y", "z"], "group": names,
              "block": block_names}
    disc = discrepancy_of(post, pos)
    if disc is not None:  # the model discrepancy: d per interior node, and its rms per draw
        posterior["d"], dims["d"] = disc, ["interior_node", "axis"]
        coords["interior_node"] = mesh.interior.astype(int)
        posterior["discrepancy_rms"] = np.sqrt(np.mean(np.sum(disc**2, axis=-1), axis=-1))
        dims["discrepancy_rms"] = []
    constant = {}
    fixed = {(p, g): v for p, g, v in layout.fixed}
    for p, arr in (("lam", lam_g), ("mu", mu_g)):
        free_g = [g for g in range(len(names)) if (p, g) not in fixed]
        if len(free_g) == len(names):
            posterior[p], dims[p] = arr, ["group"]
            continue
        # a fixed parameter is data, not a sampled variable (no constant chains, no NaN R-hat)
        if free_g:
            posterior[p], dims[p] = arr[..., free_g], [f"{p}_group"]
            coords[f"{p}_group"] = [names[g] for g in free_g]
        fg = [g for g in range(len(names)) if (p, g) in fixed]
        constant[f"{p}_fixed"] = np.array([fixed[(p, g)] for g in fg], np.float64)
        dims[f"{p}_fixed"] = [f"{p}_fixed_group"]
        coords[f"{p}_fixed_group"] = [names[g] for g in fg]
    # sample stats under ArviZ's names and types (az.bfmi, az.plot_energy read them)
    stats = {
        "lp": result.logdensity,
        "acceptance_rate": result.acceptance[..., 0],
        "block_acceptance_rate": result.acceptance,
        "diverging": np.asarray(result.divergences) > 0,
        "cg_iterations": result.cg_iterations,
        "solve_failures": result.solve_failures,
    }
    own = s_info.sample_stats  # what the kernel reports beyond acceptance, lp and CG
    gradient = "n_steps" in own
    if gradient:
        stats["n_steps"] = result.grad_evals
    if "step_size" in own:
        step = np.asarray(s_info.adapted["step_size_per_chain"], np.float64)
        stats["step_size"] = np.broadcast_to(step[:, None], (c, d))
    if "energy" in own and np.all(np.isfinite(result.energy)):
        stats["energy"] = result.energy
    if "tree_depth" in own:
        stats["tree_depth"] = result.tree_depth
    tree = to_datatree(
        posterior, sample_stats=stats, dims=dims, coords=coords, constant_data=constant,
        attrs={"units_u_b": "mm (world RAS)", "name": cfg.name,
               "tissue_coding": "label map: 1 CSF, 2 GM, 3 WM"},
    )
    tree.to_netcdf(run_dir.file("posterior.nc"))

    var_names = [v for v in ("lam", "mu", "ratio", "discrepancy_rms", "u_b") if v in posterior]
    with warnings.catch_warnings():  # fixed parameters have zero variance: NaN R-hat
        warnings.simplefilter("ignore", RuntimeWarning)
        with arviz_fast_ess():  # ArviZ's numbers, without its Python loop over lags
            summary = summary_table(tree, var_names[:-1], "u_b", "node")
        classic, split = [], []
        for v in var_names:
            x = np.asarray(tree.posterior[v].values)
            classic.append(gelman_rubin(x.reshape(c, d, -1)))
            split.append(gelman_rubin(x.reshape(c, d, -1), split=True))
    summary["rhat_classic"] = np.concatenate(classic)
    summary["rhat_classic_split"] = np.concatenate(split)
    write_text_atomic(run_dir.file("summary.csv"), summary.to_csv())

    # displacement maps: on the mesh and on the image grid (FE interpolation)
    # the nodal statistics over chunks of draws: never all (C*D, N, 3) draws at once
    u_mean = nodal_mean(problem, result)
    cov, u_sd, norm_sd_n, norm_iqr_n = nodal_spread(problem, result, u_mean)
    u_init = np.asarray(solve_position(post, init.center, rtol=cfg.solver.rtol,
                                       maxiter=cfg.solver.maxiter)[0])
    point_data = {"u_mean": u_mean, "u_sd": u_sd, "u_norm_sd": norm_sd_n,
                  "u_norm_iqr": norm_iqr_n, "u_init": u_init}
    if disc is not None:
        d_mean = np.zeros_like(u_mean)
        d_mean[mesh.interior] = disc.mean(axis=(0, 1))
        point_data["d_mean"] = d_mean
    if problem.truth is not None:
        point_data["u_true"] = problem.truth.u
        point_data["u_error"] = u_mean - problem.truth.u
    meshio.write(
        run_dir.file("mesh.vtu"),
        meshio.Mesh(mesh.nodes, [("tetra", mesh.tets)], point_data=point_data,
                    cell_data={"label": [tissue_label(mesh.tissue)]}),
    )
    located = locate_grid(mesh, problem.f)
    w, in_mesh = interpolation_matrix(mesh, problem.f, located=located)
    grid = problem.f.data.shape[:3]
    mean_img, sd_img = grid_moments_from(mesh, problem.f, u_mean, cov, located=located)
    del cov
    thinned = thinned_nodal_draws(problem, result)  # the voxel spread's and the coverage's
    norm_sd, norm_iqr = voxel_norm_spread(w, thinned)
    aff = problem.f.affine
    vol = {"displacement_mean": mean_img, "displacement_sd": sd_img,
           "displacement_norm_sd": norm_sd.reshape(grid), "displacement_norm_iqr": norm_iqr.reshape(grid),
           "displacement_init": (w @ u_init).reshape(*grid, 3)}
    if problem.truth is not None:
        vol["displacement_true"] = (problem.truth.field.data if problem.truth.field is not None
                                    else (w @ problem.truth.u).reshape(*grid, 3))
    for name, arr in vol.items():
        if name == "displacement_sd" or arr.ndim == 3:
            save_nifti(Image(arr.astype(np.float32), aff), run_dir.file(f"{name}.nii.gz"))
        else:
            save_displacement(arr, aff, run_dir.file(f"{name}.nii.gz"),
                              description=f"{name}: {FIXED_TO_MOVING}")
    save_nifti(Image(in_mesh.astype(np.uint8), aff), run_dir.file("mesh_mask.nii.gz"))
    plot_uncertainty(run_dir, problem.f, norm_iqr.reshape(grid), problem.labels)
    discrepancy = None
    if disc is not None:  # where the FE model did not explain the shift
        amplitude = (w @ np.linalg.norm(d_mean, axis=1)).reshape(grid)
        save_nifti(Image(amplitude.astype(np.float32), aff), run_dir.file("discrepancy_amplitude.nii.gz"))
        plot_brain_map(run_dir, "discrepancy.png", problem.f, amplitude, problem.labels,
                       colorbar="|E[d]| (mm)", title="model discrepancy: where the FE model "
                       "did not explain the shift, through its largest region")
        discrepancy = discrepancy_summary(problem, posterior["discrepancy_rms"], d_mean,
                                          cfg.model.discrepancy_prior.floor_mm)
    save_nifti(Image(problem.f.data.astype(np.float32), aff), run_dir.file("f.nii.gz"))
    save_nifti(Image(np.asarray(problem.m.data, np.float32), problem.m.affine), run_dir.file("m.nii.gz"))
    save_nifti(problem.labels, run_dir.file("labels.nii.gz"))

    method = cfg.output.reference
    if problem.truth is None or method == "none":
        reference = None
    else:  # the point estimate to beat
        if reference is None or method != cfg.init.registration:
            t_ref = time.perf_counter()
            reference = registration_field(problem, method, outside=cfg.synthetic.outside)
            timings = {**timings, "reference_s": time.perf_counter() - t_ref}
        save_displacement(reference.data, aff, run_dir.file("displacement_reference.nii.gz"),
                          description=f"{method} reference: {FIXED_TO_MOVING}")
    errors = error_table(problem, result, u_init, u_mean, grid=(w, in_mesh), reference=reference,
                         draws=thinned)
    del thinned
    if errors is not None and reference is not None:
        errors["reference"], errors["reference_method"] = REFERENCE_NAMES[method], method
    identification = (contraction(layout, post.prior, phi, phi_true=problem.phi_true)
                      if post.n_free else {})
    for name, r in (errors or {}).get("ratio", {}).items():
        if f"ratio_{name}" in identification:
            r["contraction"] = identification[f"ratio_{name}"]["contraction"]
            r["identified"] = identification[f"ratio_{name}"]["identified"]
    truth_ratio = None
    if errors and all("true" in errors["ratio"].get(nm, {}) for nm in names[:6]):
        truth_ratio = [errors["ratio"][nm]["true"] for nm in names[:6]]
    plot_parameters(run_dir, tree, names, truth_ratio, nodes=mesh.nodes,
                    u_true_b=None if problem.truth is None else problem.truth.u[mesh.boundary])

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
            "kind": s_info.kind,
            "prior_normaliser": cfg.model.prior_normaliser,
            "condensed": s_info.condensed,
            "cg_preconditioner": s_info.preconditioner,
            "chain_method": s_info.chain_method,
            "gradient_evaluations_per_step_mean": float(result.grad_evals.mean()),
            "divergences": int(result.divergences.sum()),
            "adapted": s_info.adapted,
            "proposal": (init_info or {}).get("proposal"),
            "chains": int(c),
            "draws_per_chain": int(d),
            "thinning": s_info.thinning,
            "steps_per_chain": int(d * s_info.thinning + s_info.warmup_steps),
            "blocks": block_names,
            # how the collapsed moves carried the displacement (sampler.carry, resolved)
            **({"collapsed_carry": cfg.collapsed_carry} if "collapsed" in block_names else {}),
            "acceptance": [float(a) for a in result.acceptance.reshape(-1, len(block_names)).mean(0)],
            # None without a warm-up (the paper's fixed kernel), not NaN (not JSON)
            "warmup_acceptance": ([float(a) for a in result.warmup_acceptance]
                                  if np.all(np.isfinite(result.warmup_acceptance)) else None),
            "rhat_classic_max": float(summary["rhat_classic"].max()),
            "rhat_classic_split_max": float(summary["rhat_classic_split"].max()),
            "rhat_split_monitored": s_info.rhat_split,
            "rhat_rank_max": float(np.nanmax(rank_rhat)),
            "ess_bulk_min": float(summary["ess_bulk"].min()),
            "ess_tail_min": float(summary["ess_tail"].min()),
            "converged": bool(result.converged),
            "stuck_chains": list(s_info.stuck_chains),
            "rhat_threshold": s_info.rhat_threshold,
            "stop": s_info.stop_rule.kind,
            "stop_rule": s_info.stop_rule.describe(),
            "rhat_rank_threshold": s_info.stop_rule.rhat_rank_max,
            "ess_min": s_info.stop_rule.ess_min,
            # per chunk: draws per chain, classic R-hat, rank R-hat, bulk and tail ESS
            "rhat_history": [[int(h[0]), *map(float, h[1:])] for h in result.rhat_history],
            "cg_iterations_per_step_mean": float(result.cg_iterations.mean()),
            "cg_iterations_per_solve_mean": (None if s_info.solves_per_step is None else
                                             float(result.cg_iterations.mean() / s_info.solves_per_step)),
            "solve_failures": int(result.solve_failures.sum()),
            "steps_per_s_per_chain": float(d * s_info.thinning / max(timings.get("sampling_s", 1e-9), 1e-9)),
        },
        "init": init_info or {},
        "truth": problem.truth_info,
        "resumed": bool(resumed),
        "n_skull_voxels_carved": problem.n_skull_carved,
        "errors": errors,
        "discrepancy": discrepancy,
        # 1 - posterior / prior variance per free parameter (logit scale) and ratio (log)
        "identification": identification,
    }
    if gradient:  # Stan's per-chain checks: divergences, tree depth cut, E-BFMI
        info["sampler"]["health"] = sampler_health(
            result.divergences, steps_per_draw=s_info.thinning,
            tree_depth=result.tree_depth if "tree_depth" in own else None,
            max_tree_depth=cfg.sampler.max_tree_depth, energy=result.energy,
            skull_barrier_mm=cfg.model.skull_barrier_mm)
    info["sampler"]["verdict"] = verdict(info["sampler"])
    write_text_atomic(run_dir.file("errors.json"), dumps_json(errors, indent=2))
    write_text_atomic(run_dir.file("run.json"), dumps_json(info, indent=2))
    path = run_dir.commit()
    return RunResult(path, tree, summary, errors, info)

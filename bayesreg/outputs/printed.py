"""What a run prints: the short table of its results and its verdict line.

:func:`format_report` is the table ``bayesreg run`` prints after the outputs (error against
the truth, the ``lam/mu`` posteriors, the model discrepancy, the sampler's figures and
checks); :func:`verdict` its last line, also kept in ``run.json``; :func:`reference_method`
names the reference registration of an ``errors.json``.  Pure functions of the run's
``errors.json`` and ``run.json`` contents (runs read back included).
"""

from __future__ import annotations

import numpy as np

from bayesreg.sampling.convergence import StopRule
from bayesreg.sampling.diagnostics import normaliser_note

__all__ = ["format_report", "verdict", "reference_method"]


def _f(x, spec: str) -> str:
    """``format(x, spec)``, or ``n/a`` for a missing or non-finite number."""
    if x is None or (isinstance(x, float) and not np.isfinite(x)):
        return "n/a"
    return format(x, spec)


def format_report(errors: dict | None, info: dict) -> str:
    """The short table the run prints (error vs truth, ratio posteriors as medians with 90%
    intervals, sampler figures), ending with the verdict line (:func:`verdict`).  Missing or
    non-finite figures (``null`` in a ``run.json`` read back) print as ``n/a``."""
    lines = []
    mesh = info.get("mesh") or {}
    if "n_nodes" in mesh:
        line = (f"mesh {mesh['n_nodes']} nodes ({mesh.get('n_boundary_nodes', '?')} boundary), "
                f"{mesh.get('n_tets', '?')} tets")
        meshing = mesh.get("meshing") or {}
        if meshing.get("target_nodes"):
            line += (f"; target {meshing['target_nodes']} within {meshing['tolerance']:.0%}: "
                     f"{'met' if meshing['within_tolerance'] else 'NOT met (closest kept)'} in "
                     f"{len(meshing['attempts'])} attempt(s), edge {_f(meshing['edge_length_mm'], '.3g')} mm")
        if meshing.get("file"):
            line += f"; read from {meshing['file']}"
        lines.append(line)
    s = info["sampler"]
    acc = ", ".join(f"{b} {_f(a, '.3f')}" for b, a in zip(s["blocks"], s["acceptance"]))
    lines.append(
        f"draws/chain {s['draws_per_chain']} (thinning {s['thinning']})  chains {s['chains']}  "
        f"acceptance {acc}"
    )
    lines.append(
        f"R-hat max: rank-normalised {_f(s['rhat_rank_max'], '.3f')}, classic "
        f"{_f(s['rhat_classic_max'], '.3f')}, split {_f(s['rhat_classic_split_max'], '.3f')}  ESS min: "
        f"bulk {_f(s['ess_bulk_min'], '.0f')}, tail {_f(s.get('ess_tail_min'), '.0f')}"
    )
    per_solve = s.get("cg_iterations_per_solve_mean")
    cg = (f"CG iterations/solve mean {_f(per_solve, '.1f')}" if per_solve is not None else
          f"CG iterations/step mean {_f(s['cg_iterations_per_step_mean'], '.1f')} (outside the trajectories)")
    if s.get("cg_preconditioner"):
        cg += f" ({s['cg_preconditioner']} preconditioner)"
    lines.append(f"{cg}  failed solves {s['solve_failures']}  steps/s per chain {_f(s['steps_per_s_per_chain'], '.1f')}")
    if (s.get("gradient_evaluations_per_step_mean") or 0) > 0:  # a gradient kernel
        lines.append(f"{s['kind']}: gradients/step {_f(s['gradient_evaluations_per_step_mean'], '.1f')}  "
                     f"divergences {s['divergences']}  prior normaliser {s['prior_normaliser']}")
    if errors and "boundary_posterior_mean_mm" in errors:
        lines.append("error vs truth (mm)           median    95th     max")
        rows = [("boundary_initial_mm", "boundary, initial"),
                ("boundary_posterior_mean_mm", "boundary, posterior mean"),
                ("all_nodes_posterior_mean_mm", "all nodes, posterior mean")]
        if "boundary_reference_mm" in errors:
            rows.append(("boundary_reference_mm", f"boundary, {reference_method(errors)}"))
        for key, label in rows:
            e = errors[key]
            lines.append(f"  {label:<27} {_f(e['median'], '7.3f')} {_f(e['q95'], '7.3f')} {_f(e['max'], '7.3f')}")
        lines.append(f"  MSE all nodes {_f(errors['mse_all_nodes_mm2'], '.4f')} mm^2")
        brain = errors.get("brain")
        if brain:
            lines.append("  brain voxels: MSE (mm^2) / 95th (mm): " + ", ".join(
                f"{k.replace('_', ' ')} {_f(brain['mse_mm2'][k], '.4f')} / {_f(brain['q95_mm'][k], '.3f')}"
                for k in brain["mse_mm2"]))
        cm = errors.get("coverage_moving")
        if cm:
            lines.append(f"  90% interval coverage where the truth moves >= "
                         f"{errors.get('moving_threshold_mm', 1.0):g} mm: {_f(cm.get('0.9'), '.2f')} "
                         f"({cm['n_components']} components); boundary "
                         f"{_f(errors['coverage_boundary'].get('0.9'), '.2f')}")
        fit = errors.get("image_fit")
        if fit:
            lines.append(f"  images' term -E_s/T_s: truth {_f(fit['truth'], '.1f')}, posterior mean "
                         f"{_f(fit['posterior_mean'], '.1f')} ({_f(fit['gain_nats'], '+.1f')} nats: "
                         "what the posterior fits beyond the truth, noise-free images' residual "
                         "included; benchmarks/residual.py)")
        best = errors.get("mesh_best_fit")
        if best and best.get("coverage_moving"):
            lines.append(f"  the mesh's best fit to the truth (brain MSE "
                         f"{_f(best['brain_mse_mm2'], '.4f')} mm^2; "
                         f"{_f(best['nodes_from_truth_mm']['median'], '.3f')} mm median from the "
                         f"truth at the nodes): 90% coverage of it "
                         f"{_f(best['coverage_moving'].get('0.9'), '.2f')}")
    if errors:
        lines.append("lam/mu posterior       median        5%       95%     truth  contraction")
        for name, r in errors["ratio"].items():
            tr = f"{_f(r['true'], '9.4g')}" if "true" in r else "        -"
            mid = r.get("median", r.get("mean"))  # (runs written before medians were kept)
            c = r.get("contraction")
            flag = "" if c is None or r.get("identified") else "  not identified by the images"
            lines.append(f"  {name:<14} {_f(mid, '9.4g')} {_f(r['q05'], '9.4g')} {_f(r['q95'], '9.4g')} "
                         f"{tr} {_f(c, '12.2f') if c is not None else '           -'}{flag}")
    disc = info.get("discrepancy")
    if disc:
        r = disc["rms_mm"]
        lines.append(f"model discrepancy: rms |d| per interior node {_f(r['median'], '.3f')} mm "
                     f"(90%: {_f(r['q05'], '.3f')}-{_f(r['q95'], '.3f')}), largest |E[d]| "
                     f"{_f(disc['mean_norm_max_mm'], '.2f')} mm (discrepancy_amplitude.nii.gz)")
    ident = info.get("identification") or {}
    edge = [k for k, v in ident.items() if v.get("at_prior_edge") and not v.get("truth_at_prior_edge")]
    if edge:
        lines.append(f"on the prior's edge: {', '.join(edge)} (posterior median in the outer 1% of "
                     "the prior's support: a misfit the model cannot make, paid with the "
                     "parameters?)")
    edge = [k for k, v in ident.items() if v.get("at_prior_edge") and v.get("truth_at_prior_edge")]
    if edge:
        lines.append(f"on the prior's edge with their truths: {', '.join(edge)} (posterior median "
                     "and truth in the outer 1% of the prior's support)")
    lines.extend(f"model check: {n}" for n in [normaliser_note(info)] if n)
    lines.extend(f"sampler check: {w}" for w in (s.get("health") or {}).get("warnings", []))
    lines.append(verdict(s))
    return "\n".join(lines)


def verdict(s: dict) -> str:
    """The plain last line of a run's summary: converged or not, against which criterion.

    Parameters
    ----------
    s : dict
        ``run.json["sampler"]``: ``stop`` (the run's rule, ``"rank"`` or ``"paper"``; older
        runs: the paper's), ``converged`` (that rule met), ``rhat_threshold``,
        ``rhat_rank_threshold``, ``ess_min``, ``rhat_classic_max`` /
        ``rhat_classic_split_max``, ``rhat_rank_max``, ``ess_bulk_min``, ``ess_tail_min``
        (absent in older runs), ``stuck_chains``, ``draws_per_chain``.

    Returns
    -------
    str
        ``"verdict: converged ..."`` only where today's criterion (rank-normalised R-hat
        <= 1.01, bulk and tail ESS >= 400, or the run's own thresholds) is met, and under
        the paper's rule that rule too; ``"verdict: NOT converged ..."`` otherwise, with the
        figures that fail.
    """
    stuck = s.get("stuck_chains") or []
    if stuck:
        return (f"verdict: NOT converged: chains {stuck} never moved while sampling; this run's "
                "summaries do not describe the posterior")
    split = bool(s.get("rhat_split_monitored"))
    classic = s.get("rhat_classic_split_max" if split else "rhat_classic_max")
    paper = f"{'split ' if split else ''}classic R-hat {_f(classic, '.3f')}, needs < {s.get('rhat_threshold')}"
    rank, bulk, tail = s.get("rhat_rank_max"), s.get("ess_bulk_min"), s.get("ess_tail_min")
    # today's criterion with the run's thresholds (older runs: the defaults); a figure that
    # is missing (null in run.json: not finite) fails it, an absent tail ESS (older runs) not
    default = StopRule()
    today = StopRule("rank", rhat_rank_max=s.get("rhat_rank_threshold", default.rhat_rank_max),
                     ess_min=s.get("ess_min", default.ess_min))
    rank_max, ess_min = today.rhat_rank_max, today.ess_min
    modern_ok = today.met(np.nan, *(np.nan if x is None else x for x in (rank, bulk)),
                          np.inf if tail is None else tail)
    modern = (f"rank-normalised R-hat {_f(rank, '.3f')} (needs <= {rank_max:g}), bulk ESS "
              f"{_f(bulk, '.0f')}" + ("" if tail is None else f", tail ESS {_f(tail, '.0f')}")
              + f" (need >= {ess_min:g})")
    if s.get("stop", "paper") == "rank":  # the run's rule is today's
        if s.get("converged") and modern_ok:
            return f"verdict: converged: {modern}"
        return (f"verdict: NOT converged: {s.get('draws_per_chain')} draws per chain (max_draws) "
                f"without meeting the stop rule: {modern}; means and intervals are not yet "
                "reliable (a larger sampler.max_draws, or a faster-mixing sampler)")
    if s.get("converged") and modern_ok:
        return f"verdict: converged by the paper's rule ({paper}) and by today's: {modern}"
    if s.get("converged"):
        return (f"verdict: NOT converged by today's criterion ({modern}), although the paper's rule "
                f"stopped the run ({paper}); means and intervals are not yet reliable")
    return (f"verdict: NOT converged: {s.get('draws_per_chain')} draws per chain without meeting the "
            f"paper's rule ({paper}); {modern}; these summaries do not describe the posterior")


def reference_method(errors: dict) -> str:
    """The ``output.reference`` method an ``errors.json`` names (``"tvl1"``, ``"ilk"``,
    ``"syn"``), also of runs written before ``reference_method`` was recorded (the last
    word of scikit-image's function name); ``"reference"`` where it names none."""
    return errors.get("reference_method") or errors.get("reference", "reference").rsplit("_", 1)[-1]

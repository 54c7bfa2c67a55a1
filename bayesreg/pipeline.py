"""The main job: a config in, a run directory out.

:func:`run` loads the config, builds the problem (:func:`bayesreg.model.problem.prepare`), finds
the starts (:func:`bayesreg.inference.initialisation.initialise`), samples (:func:`sample_problem`) and
writes the run directory (:func:`bayesreg.outputs.write.write_outputs`), checkpointing as it goes
(:mod:`bayesreg.checkpoint`) so that ``resume`` continues a killed run.
"""

from __future__ import annotations

import time

import jax
import numpy as np

from bayesreg.checkpoint import Checkpoint
from bayesreg.config import Config, load_config, override_config
from bayesreg.inference.initialisation import Initialisation, initialise, registration_field
from bayesreg.jaxconfig import configure_jax
from bayesreg.outputs.result import RunResult
from bayesreg.outputs.write import write_outputs
from bayesreg.model.posterior import elastic_groups
from bayesreg.model.problem import Problem, assemble, at_start, make_data
from bayesreg.rundir import RunDirectory
from bayesreg.sampling.driver import SamplerResult, sample
from bayesreg.sampling.kernels.gibbs import rebuilt_center
from bayesreg.stages import Stages
from bayesreg.inference.targets import sampling_algorithm

__all__ = ["sample_problem", "run", "RunInterrupted"]


def sample_problem(problem: Problem, cfg: Config, init: Initialisation | None = None, *,
                   on_chunk=None, resume=None, resume_draws=None,
                   on_warmup_chunk=None) -> tuple[SamplerResult, Initialisation]:
    """Initialise (unless ``init`` is given) and sample, as ``cfg.sampler`` says.

    The monitored estimands are every boundary coordinate, every free parameter and the
    ``lam/mu`` ratio of every group.

    Parameters
    ----------
    problem : Problem
    cfg : Config
    init : Initialisation, optional
        Starts and proposal scales (default :func:`bayesreg.inference.initialisation.initialise`).
    on_chunk, resume, resume_draws, on_warmup_chunk
        Checkpointing (:func:`bayesreg.sampling.driver.sample`; see :func:`run`).

    Returns
    -------
    result : SamplerResult
    init : Initialisation
    """
    init = init or initialise(problem, cfg)
    problem = at_start(problem, cfg, init)
    post = problem.posterior
    nb3 = post.n_displacement

    def estimands(draws):
        # boundary coordinates (and a discrepancy's), free parameters and the lam/mu ratios
        phi = draws[..., nb3:]
        lam_g, mu_g = (np.asarray(a) for a in elastic_groups(post, phi))
        return np.concatenate([draws, lam_g / mu_g], axis=-1)

    s = cfg.sampler
    common = dict(thinning=s.thinning, warmup_steps=s.warmup_steps, max_draws=s.max_draws,
                  min_draws=s.min_draws, chunk_draws=s.chunk_draws,
                  rhat_threshold=s.rhat_threshold, rhat_split=s.rhat_split, stop=s.stop,
                  rhat_rank_max=s.rhat_rank_max, ess_min=s.ess_min, estimands=estimands,
                  progress=cfg.output.progress, on_chunk=on_chunk, resume=resume,
                  resume_draws=resume_draws, chain_method=s.chain_method,
                  on_warmup_chunk=on_warmup_chunk)
    result = sample(jax.random.key(cfg.seed), sampling_algorithm(problem, cfg, init), init.x0,
                    **common)
    return result, init


def check_optional_packages(cfg: Config) -> None:
    """The optional packages ``cfg`` needs are installed (checked before anything is written
    or sampled, rather than found missing in the outputs stage).

    Raises
    ------
    ConfigError
        ``output.reference: syn`` without ANTsPy.
    """
    import importlib.util

    from bayesreg.config import ConfigError

    if cfg.output.reference == "syn" and importlib.util.find_spec("ants") is None:
        raise ConfigError("output.reference: syn needs ANTsPy, which is not installed: pip "
                          "install 'bayesreg[ants]' (or antspyx; wheels for Linux x86_64 and "
                          "macOS), or choose output.reference: tvl1 | ilk | none")


def run(config=None, *, out=None, overrides=None, overwrite=None, progress=None,
        resume=None) -> RunResult:
    """Run the whole job and write its run directory.

    Calls :func:`bayesreg.configure_jax` first.  A new run that fails before its sampling
    starts (an error in the data, the mesh or the starts) removes its run directory and puts
    back the one it replaced; one that fails or is interrupted later keeps its checkpoint
    for ``resume``.

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
        interrupted (same draws).  ``config``, ``out`` and ``overwrite`` must then be omitted;
        ``overrides`` may only change how long it runs (:data:`RESUME_KEYS`: the stop rule,
        its thresholds, the draw bounds; the saved config is updated), so that a run can be
        taken on to a stricter rule or more draws without losing the draws it has.

    Returns
    -------
    bayesreg.outputs.result.RunResult

    Raises
    ------
    FileExistsError
        If the run directory exists and is not empty and ``overwrite`` is false (or it is
        not a run directory), or a run to resume is already finished.
    FileNotFoundError
        If ``resume`` names a directory without a checkpoint.
    ConfigError
        On a bad config, override or saved config (the message names the key or file).
    ValueError
        ``resume`` given with a config, ``out``, ``overwrite`` or an override of a key
        outside :data:`RESUME_KEYS`; bad data.

    Examples
    --------
    The quickstart's problem on tiny settings (a coarse mesh on 3 mm images, two chains of
    the paper's random walk, a few draws; about 40 s on a 2-core CPU, so the test suite runs
    the same call in notebook 01 instead of here):

    >>> import bayesreg
    >>> tiny = ["data.resolution_mm=3.0", "mesh.edge_length_mm=26", "sampler.kind=rwmh",
    ...         "sampler.chains=2", "sampler.proposal=isotropic", "init.method=perturb",
    ...         "sampler.warmup_steps=20", "sampler.thinning=1", "sampler.chunk_draws=10",
    ...         "sampler.max_draws=10", "sampler.min_draws=10", "output.reference=false"]
    >>> result = bayesreg.run("configs/quickstart.yaml", out=getfixture("tmp_path") / "run",
    ...                       overrides=tiny, progress=False)  # doctest: +SKIP
    >>> result.posterior.posterior["u_b"].dims  # doctest: +SKIP
    ('chain', 'draw', 'node', 'axis')
    >>> sorted(result.errors)[:2]  # doctest: +SKIP
    ['all_nodes_posterior_mean_mm', 'boundary_initial_mm']
    """
    configure_jax()
    t0 = time.perf_counter()
    if resume is not None:
        if config is not None or out is not None or overwrite:
            raise ValueError("resume continues a run with its own config and directory: give no "
                             "config, out or overwrite")
        _check_resume_overrides(overrides)
        run_dir = RunDirectory(resume, resume=True)  # locked from here on
        ckpt = Checkpoint(run_dir.path)
        try:
            cfg = ckpt.load_config()
            if overrides:
                cfg = override_config(cfg, overrides)
                ckpt.save_config(cfg)
        except BaseException:
            run_dir.release()
            raise
        cfg.output.dir = run_dir.path
    else:
        cfg = config if isinstance(config, Config) else load_config(config, overrides=overrides)
        values = {k: v for k, v in (("output__dir", None if out is None else str(out)),
                                    ("output__overwrite", overwrite)) if v is not None}
        # a copy (the caller's config is not changed), overrides applied to a Config object
        cfg = override_config(cfg, overrides if isinstance(config, Config) else None, **values)
        check_optional_packages(cfg)
        inputs = {"data.fixed": cfg.data.fixed, "data.moving": cfg.data.moving,
                  "data.labels": cfg.data.labels, "mesh.file": cfg.mesh.file,
                  "synthetic.field": cfg.synthetic.field}
        run_dir = RunDirectory(cfg.output.dir, overwrite=cfg.output.overwrite,  # fails early
                               inputs={k: v for k, v in inputs.items() if v is not None})
        ckpt = Checkpoint(run_dir.path)
    if progress is not None:
        cfg.output.progress = progress
    # one line per finished stage, whatever output.progress (the bars) says: a batch log
    # shows how far a killed run came
    stages = Stages(progress=True)
    resumable = False  # whether the checkpoint holds a problem and starts to resume from
    try:
        if resume is None and cfg.output.checkpoint:
            ckpt.save_config(cfg)
        saved = resume is not None and ckpt.problem_path.is_file()
        data = ckpt.load_problem() if saved else make_data(cfg, stages)
        with stages.stage("posterior"):
            problem = assemble(cfg, data)
        if cfg.output.checkpoint and not saved:
            ckpt.save_problem(problem.data)
        init = ckpt.load_init() if resume is not None else None
        flow = None  # a registration start's optical flow: also the outputs' reference
        if init is None:
            with stages.stage("starts"):
                if cfg.init.start == "registration":
                    t = time.perf_counter()
                    flow = registration_field(problem, cfg.init.registration,
                                              outside=cfg.synthetic.outside)
                    t = time.perf_counter() - t
                init = initialise(problem, cfg, flow=flow)
                if flow is not None:
                    init.info.update(registration_s=t, init_s=init.info["init_s"] + t)
                stages.tell(starts_line(init.info, len(init.x0)))
            if cfg.output.checkpoint:
                ckpt.save_init(init)
        problem = at_start(problem, cfg, init)
        resumable = cfg.output.checkpoint
        state = ckpt.load_state() if resume is not None else None
        warm = ckpt.load_warmup() if resume is not None and state is None else None

        def warmup_ended(checkpoint):  # (the tuned values: a gradient kernel's GibbsParams)
            center = rebuilt_center(checkpoint.sigma) if cfg.sampler.gradient else None
            if center is not None:
                stages.tell("the normaliser's surrogate rebuilt at the chains' median parameters "
                            "(" + ", ".join(f"{v:.3g}" for v in center[0]) + ")")
            stages.switch("sampling")

        def on_chunk(checkpoint, out):
            if out is None:  # the warm-up ended
                warmup_ended(checkpoint)
            ckpt.on_chunk(checkpoint, out)

        with stages.stage("warm-up" if state is None else "sampling"):
            result, init = sample_problem(
                problem, cfg, init,
                on_chunk=on_chunk if cfg.output.checkpoint else
                (lambda c, out: warmup_ended(c) if out is None else None),
                resume=warm if state is None else state[0],
                resume_draws=None if state is None else state[1],
                on_warmup_chunk=ckpt.on_warmup_chunk if cfg.output.checkpoint else None,
            )
        init_info = dict(init.info)
        timings = {**problem.timings, "init_s": init_info.pop("init_s", float("nan")),
                   **result.timings, "total_before_outputs_s": time.perf_counter() - t0}
        with stages.stage("outputs"):
            res = write_outputs(run_dir, cfg, problem, result, init, timings, init_info,
                                resumed=resume is not None, reference=flow)
        ckpt.clear_progress()
        return res
    except KeyboardInterrupt as exc:
        raise RunInterrupted(_abandon(run_dir, ckpt, stages, resume, resumable)) from exc
    except BaseException:
        _abandon(run_dir, ckpt, stages, resume, resumable)
        raise
    finally:
        run_dir.release()


#: The config keys a resumed run may change (``run(resume=..., overrides=...)``, ``bayesreg
#: run --resume DIR --set KEY=VALUE``): how long the chains run, never what they sample.
RESUME_KEYS = ("sampler.stop", "sampler.max_draws", "sampler.min_draws", "sampler.rhat_rank_max",
               "sampler.ess_min", "sampler.rhat_threshold", "sampler.rhat_split")


def _check_resume_overrides(overrides) -> None:
    """Refuse, by name, an override a resumed run cannot take (:data:`RESUME_KEYS`)."""
    for item in overrides or ():
        key = str(item).split("=", 1)[0].strip()
        if "=" not in str(item) or key not in RESUME_KEYS:
            raise ValueError(
                f"resume: cannot change {key!r}: a resumed run keeps its model, data, starts "
                f"and sampler; only how long it runs may change ({', '.join(RESUME_KEYS)})")


def starts_line(info: dict, chains: int) -> str:
    """One line on how the chains' starts were made (the mode search's gain and why it
    stopped)."""
    line = f"{chains} chains, start {info.get('start', '?')}"
    if info.get("method") == "mode":
        line += (f"; mode search log p {info['logp_start']:.6g} -> {info['logp_mode']:.6g} in "
                 f"{info['iterations']} iterations ({info['message']})")
    else:
        line += f", {info.get('method', '?')}"
    orth = info.get("orthogonal_search")
    if orth:
        line += (f"; then, the discrepancy orthogonal to the sensitivities there, log p "
                 f"{orth['logp_start']:.6g} -> {orth['logp_mode']:.6g} in {orth['iterations']} "
                 "iterations")
    return line


class RunInterrupted(KeyboardInterrupt):
    """A run stopped by an interrupt (Ctrl-C; SIGTERM under the CLI); its message says where it
    stopped and what was kept."""


def _abandon(run_dir: RunDirectory, ckpt: Checkpoint, stages: Stages, resume, resumable: bool) -> str:
    """Leave the run directory of a run that stops before its end as the rules say, and say
    how it was left: an ``--overwrite`` puts back the run it replaced (this run's partial
    directory goes); a new run stopped before anything resumable was saved leaves nothing;
    otherwise the checkpoint stays for ``--resume``."""
    where = f"during the {stages.current}" if stages.current else "before it started"
    path = run_dir.path
    if (path / "run.json").is_file() and run_dir.replaced is None and not (path / ".outputs-partial").exists():
        return f"interrupted after its outputs were written: the run in {path} is finished"
    if run_dir.replaced is not None:
        run_dir.restore()
        return (f"interrupted {where}: the run that was in {path} is back in place (this "
                "run's partial results were discarded)")
    if resume is None and not resumable:
        run_dir.rollback()
        return f"interrupted {where}: nothing was kept"
    if stages.current == "warm-up" and ckpt.warmup_chunks_done:
        where = f"after warm-up chunk {ckpt.warmup_chunks_done}"
    elif stages.current == "sampling" and ckpt.chunks_done:
        where = f"after chunk {ckpt.chunks_done}"
    elif stages.current == "sampling" and ckpt.chunks_done == 0:
        where = "after the warm-up"
    return f"interrupted {where}; continue with `bayesreg run --resume {path}`"

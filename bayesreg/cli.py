"""Command line.

``bayesreg run CONFIG [--out DIR] [--set key=value ...] [--overwrite]``
    one run (:func:`bayesreg.run`); ``bayesreg run --resume RUN_DIR [--set sampler.stop=rank
    ...]`` continues a killed one (``--set`` only for the stop rule and the draw bounds).
``bayesreg reproduce [--variant paper|nuts] [--out DIR] [--set key=value ...]``
    the paper's two experiments (``configs/paper_uniform.yaml``,
    ``configs/paper_three_compartment.yaml``; ``--variant nuts``: their gradient-sampler
    variants ``configs/paper_*_nuts.yaml``) and their report (Tables 1-2, Figures 2-5).
``bayesreg report RUN_DIR ... --out DIR``
    the report of finished runs (``bayesreg report SWEEP_DIR``: a sweep's tables, rebuilt).
``bayesreg sweep SWEEP.yaml [--scheduler ADDRESS] [--workers N]``
    many runs over config keys on Dask distributed (:mod:`bayesreg.experiments.sweep`); running it
    again finishes what is left.
``bayesreg export RUN_DIR --format itk|ants|slicer|nifti [--draws K] [--out DIR]``
    the posterior mean (and K draws) as transforms ITK, ANTs and 3D Slicer apply
    (:func:`bayesreg.apply.export`).
``bayesreg apply RUN_DIR INPUT --out OUT [--as image|labels|points] [--draws K]``
    an image through the posterior mean, a label map through posterior draws (per-label
    probability, most probable label), points with their posterior and 95% ellipsoids
    (:mod:`bayesreg.apply`).
``bayesreg --version``
    the package's version (``run.json`` records it with its dependencies' versions).

Exit status 0 on success; 2 on bad input or a failed stage (the message names the problem and
what to change), and for a sweep with a run not finished; with ``run --strict``, 3 when chains
never moved and 4 when the stop rule was not met by ``max_draws``; 130 when interrupted
(Ctrl-C or SIGTERM; one line says what was kept).
"""

from __future__ import annotations

import argparse
import os
import signal
import sys
from pathlib import Path

import numpy as np

from bayesreg import __version__
from bayesreg.config import ConfigError
from bayesreg.jaxconfig import configure_jax
from bayesreg.outputs.printed import format_report
from bayesreg.pipeline import RunInterrupted, run
from bayesreg.report import write_report
from bayesreg.stages import StageError
from bayesreg.experiments.sweep import run_or_resume, run_sweep, sweep_report

__all__ = ["main", "console", "PAPER_CONFIGS"]

PAPER_CONFIGS = {
    "three_compartment": "paper_three_compartment.yaml",
    "uniform": "paper_uniform.yaml",
}


def _parser():
    p = argparse.ArgumentParser(prog="bayesreg", description="Bayesian biomechanical registration")
    p.add_argument("--version", action="version", version=f"%(prog)s {__version__}")
    sub = p.add_subparsers(dest="command", required=True)
    r = sub.add_parser("run", help="run a YAML config end to end (or --resume a killed run)")
    r.add_argument("config", nargs="?", help="YAML config file (omit with --resume)")
    r.add_argument("--out", help="run directory (default: output.dir of the config)")
    r.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="override a config value, e.g. --set sampler.max_draws=500 (repeatable)")
    r.add_argument("--overwrite", action="store_true", help="replace an existing run directory")
    r.add_argument("--resume", metavar="RUN_DIR",
                   help="continue the unfinished run in RUN_DIR (same draws as an uninterrupted "
                   "run); --set may then change only the stop rule and the draw bounds "
                   "(sampler.stop, max_draws, min_draws, rhat_rank_max, ess_min, "
                   "rhat_threshold, rhat_split)")
    r.add_argument("--no-progress", action="store_true",
                   help="no progress bars (the line per finished stage stays)")
    r.add_argument("--strict", action="store_true",
                   help="exit with status 3 when chains never moved (their draws are their start), "
                        "4 when the stop rule was not met by sampler.max_draws")

    q = sub.add_parser("reproduce", help="the paper's two experiments and their report")
    q.add_argument("--variant", choices=("paper", "nuts"), default="paper",
                   help="paper: the paper's RW-MH (configs/paper_*.yaml); nuts: the same experiments "
                        "sampled by NUTS (configs/paper_*_nuts.yaml)")
    q.add_argument("--out", default=None,
                   help="folder of the two runs and the report (default runs/paper, runs/paper_nuts)")
    q.add_argument("--configs", default=None,
                   help="folder holding paper_uniform.yaml and paper_three_compartment.yaml "
                        "(default: configs/ of the working folder or of the source tree)")
    q.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="override a value in both configs (repeatable)")
    q.add_argument("--no-progress", action="store_true",
                   help="no progress bars (the line per finished stage stays)")

    w = sub.add_parser("report", help="tables and figures of finished runs, or a sweep's tables")
    w.add_argument("runs", nargs="+", metavar="[LABEL=]RUN_DIR",
                   help="run directories, or one sweep folder (its tables are rebuilt from its runs)")
    w.add_argument("--out", help="report directory (required for runs; a sweep's default: its folder)")
    w.add_argument("--overwrite", action="store_true", help="replace an existing report directory")

    s = sub.add_parser("sweep", help="many runs over config keys, on Dask distributed")
    s.add_argument("sweep", help="sweep file (YAML: name, configs, set, grid, runs, dir)")
    s.add_argument("--scheduler", metavar="ADDRESS",
                   help="a running Dask scheduler (tcp://host:8786); default a LocalCluster")
    s.add_argument("--workers", type=int, default=None,
                   help="LocalCluster worker processes, one run each (default: one per core)")
    s.add_argument("--max-start-mm", type=float, default=1.0,
                   help="status 'bad start' for a run whose chains start further than this from "
                        "the truth (median over boundary nodes, mm; default 1)")
    c = sub.add_parser("calibrate", help="simulation-based calibration of the posterior on a "
                       "small problem (truths from the prior, data from the likelihood)")
    c.add_argument("spec", nargs="?", help="calibration file (YAML; default: every default, "
                   "as configs/calibration.yaml)")
    c.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="override a value, e.g. --set replicas=20 (repeatable)")
    c.add_argument("--out", help="output folder (default: dir of the file)")
    c.add_argument("--strict", action="store_true",
                   help="exit with status 5 when the posterior is not calibrated")
    e = sub.add_parser("export", help="a run's posterior as ITK/ANTs/Slicer/NIfTI transforms")
    e.add_argument("run_dir", help="a finished run directory")
    e.add_argument("--format", default="itk", choices=["itk", "ants", "slicer", "nifti"])
    e.add_argument("--draws", type=int, default=0, help="also write K posterior draws (default 0)")
    e.add_argument("--out", help="folder (default RUN_DIR/export/FORMAT)")
    e.add_argument("--no-inverse", action="store_true", help="skip the moving-to-fixed fields")

    a = sub.add_parser("apply", help="carry an image, a label map or points through the posterior")
    a.add_argument("run_dir", help="a finished run directory")
    a.add_argument("input", help="NIfTI image or label map; points as .csv (x,y,z RAS mm), "
                                 ".mrk.json or .fcsv (3D Slicer)")
    a.add_argument("--out", required=True, help="output file (.nii.gz, or .csv / .mrk.json for points)")
    a.add_argument("--as", dest="kind", choices=["auto", "image", "labels", "points"], default="auto",
                   help="what INPUT is (auto: points by extension, labels for an integer NIfTI)")
    a.add_argument("--direction", choices=["to-moving", "to-fixed"], default=None,
                   help="images and labels: from the fixed (pre-operative) frame to the moving "
                        "grid, or back (default: to-moving for labels, to-fixed for images)")
    a.add_argument("--draws", type=int, default=100,
                   help="posterior draws for labels and points (default 100; 0: every draw)")
    a.add_argument("--order", type=int, default=1, help="image interpolation order (0-5; default 1)")
    a.add_argument("--truth", metavar="POINTS|synthetic",
                   help="points: their true moving-frame positions (same order), or 'synthetic' "
                        "for the run's synthetic truth; adds the target registration error")
    return p


def _input_kind(path: Path, kind: str) -> str:
    if kind != "auto":
        return kind
    name = path.name.lower()
    if name.endswith((".csv", ".fcsv", ".json")):
        return "points"
    import nibabel as nib

    return "labels" if np.issubdtype(nib.load(str(path)).get_data_dtype(), np.integer) else "image"


def _apply(args) -> str:
    from bayesreg import apply as A
    from bayesreg.data.images import Image, load_nifti, save_nifti
    from bayesreg.interop.transforms import displace_points

    rp = A.load_posterior(args.run_dir)
    path, out = Path(args.input), Path(args.out)
    kind = _input_kind(path, args.kind)
    draws = None if args.draws == 0 else args.draws
    out.parent.mkdir(parents=True, exist_ok=True)
    if kind == "points":
        names, pts = A.read_points(path)
        pp = A.map_points(rp, pts, names, draws=draws)
        errors = None
        if args.truth == "synthetic":
            if rp.u_true is None:
                raise ValueError("apply: --truth synthetic needs a synthetic run")
            errors = A.target_errors(pp, displace_points(rp.mesh, rp.u_true, pts)[0])
        elif args.truth:
            errors = A.target_errors(pp, A.read_points(args.truth)[1])
        A.write_points(out, pp, errors)
        msg = f"{len(pts)} points ({int(pp.inside.sum())} inside the mesh) -> {out}"
        if errors is not None:
            msg += (f"; TRE median {errors['tre_median_mm']:.3f} mm, max {errors['tre_max_mm']:.3f} mm,"
                    f" truth inside its 95% ellipsoid for {errors['coverage_95']:.0%}")
        return msg
    img = load_nifti(path)
    if kind == "labels":
        lp = A.warp_labels(rp, img, direction=args.direction or "to-moving", draws=draws)
        p1, p2 = A.save_label_posterior(lp, out)
        return f"labels {list(map(int, lp.values))} through {lp.n_draws} draws -> {p1}, {p2}"
    res = A.warp_image(rp, Image(np.asarray(img.data, np.float64), img.affine),
                       direction=args.direction or "to-fixed", order=args.order)
    save_nifti(Image(res.data.astype(np.float32), res.affine), out)
    return f"image -> {out}"


def _configs_dir(arg) -> Path:
    if arg is not None:
        return Path(arg)
    for cand in (Path("configs"), Path(__file__).resolve().parent.parent / "configs"):
        if all((cand / f).is_file() for f in PAPER_CONFIGS.values()):
            return cand
    raise FileNotFoundError("paper configs not found: pass --configs DIR (holding "
                            + ", ".join(PAPER_CONFIGS.values()) + ")")


def _report_runs(items) -> dict:
    """``{label: run directory}`` from ``[LABEL=]RUN_DIR`` items of ``bayesreg report``.

    An item that is an existing directory is a run directory whatever it holds (a path may
    contain ``=``: ``runs/t_r=300``); otherwise the label ends at the first ``=``.  Without
    a label, the directory's name is the label.

    Raises
    ------
    ValueError
        An empty label, or two runs with one label (the report would show one of them).
    """
    runs: dict = {}
    for item in items:
        if "=" in item and not Path(item).is_dir():
            label, _, path = item.partition("=")
            if not label:
                raise ValueError(f"report: empty label in {item!r} (give LABEL=RUN_DIR or RUN_DIR)")
        else:
            label, path = Path(item).name, item
        if label in runs:
            raise ValueError(f"report: two runs are labelled {label!r} ({runs[label]} and {path}): "
                             f"give each its own label, e.g. one={runs[label]} two={path}")
        runs[label] = Path(path)
    return runs


#: Exit statuses of the ``bayesreg`` command.
EXIT_OK, EXIT_ERROR, EXIT_STUCK, EXIT_NOT_CONVERGED, EXIT_INTERRUPTED = 0, 2, 3, 4, 130
EXIT_NOT_CALIBRATED = 5


def _interrupt_on_sigterm():
    """Make SIGTERM (``kill PID``) interrupt the run as Ctrl-C does, so that it leaves its
    directory as the rules say; returns the handler to put back."""
    def handler(signum, frame):
        raise KeyboardInterrupt(f"signal {signum}")

    try:
        return signal.signal(signal.SIGTERM, handler)
    except ValueError:  # not the main thread (an embedding application's choice)
        return None


def main(argv=None) -> int:
    """The ``bayesreg`` command; returns the exit status.

    0 success; 2 bad input or a failed stage (the message names the stage and what to
    change); with ``--strict``, 3 a run whose chains never moved, 4 a run that did not meet its
    stop rule by ``sampler.max_draws``; 130 interrupted (Ctrl-C,
    SIGTERM: one line says what was kept, and how to continue).
    """
    args = _parser().parse_args(argv)
    configure_jax()

    # bad input, a failed stage and file-system errors (a path that is a file, a missing or
    # damaged file, no permission, a full disk) end with their message and exit status 2,
    # not a traceback
    errors = (ConfigError, OSError, ValueError, StageError)
    progress = False if getattr(args, "no_progress", False) else None
    previous = _interrupt_on_sigterm()
    status = EXIT_OK
    try:
        if args.command == "run":
            if (args.config is None) == (args.resume is None):
                raise ValueError("give either CONFIG or --resume RUN_DIR")
            if args.resume is not None:
                if args.out or args.overwrite:
                    raise ValueError("--resume continues a run in its own directory: no "
                                     "--out/--overwrite")
                res = run(resume=args.resume, overrides=args.set, progress=progress)
            else:
                res = run(args.config, out=args.out, overrides=args.set,
                          overwrite=True if args.overwrite else None, progress=progress)
            print(format_report(res.errors, res.info))
            t = res.info["timings_s"]
            print(f"wall time before outputs {t.get('total_before_outputs_s', float('nan')):.1f} s; "
                  f"outputs in {res.dir}")
            if args.strict and res.info["sampler"].get("stuck_chains"):
                status = EXIT_STUCK
            elif args.strict and not res.info["sampler"].get("converged"):
                status = EXIT_NOT_CONVERGED
        elif args.command == "reproduce":
            cdir = _configs_dir(args.configs)
            out = Path(args.out or ("runs/paper" if args.variant == "paper" else f"runs/paper_{args.variant}"))
            runs = {}
            for label, fname in PAPER_CONFIGS.items():
                if args.variant != "paper":
                    fname = fname.replace(".yaml", f"_{args.variant}.yaml")
                print(f"== {label}: {cdir / fname}")
                res, _ = run_or_resume(cdir / fname, out / label, args.set, progress)
                print(format_report(res.info.get("errors"), res.info))
                runs[label] = res.dir
            path = write_report(runs, out / "report", overwrite=True)
            print(f"report in {path / 'report.md'}")
        elif args.command == "report":
            if len(args.runs) == 1 and (Path(args.runs[0]) / "sweep.json").is_file():
                path = sweep_report(args.runs[0], args.out)
                print(f"sweep tables in {path / 'sweep.md'} and {path / 'sweep.csv'}")
            else:
                if args.out is None:
                    raise ValueError("report: give --out DIR for the report of runs")
                path = write_report(_report_runs(args.runs), args.out, overwrite=args.overwrite)
                print(f"report in {path / 'report.md'}")
        elif args.command == "export":
            from bayesreg.apply import export

            man = export(args.run_dir, args.format, draws=args.draws, out=args.out,
                         inverse=not args.no_inverse)
            folder = Path(args.out) if args.out else Path(args.run_dir) / "export" / args.format
            print(f"{len(man['files'])} transform(s) ({args.format}) in {folder}; "
                  f"directions in {folder / 'transforms.json'}")
        elif args.command == "apply":
            print(_apply(args))
        elif args.command == "calibrate":
            from bayesreg.experiments.calibration import calibrate, load_spec, table

            summary = calibrate(load_spec(args.spec, args.set), args.out)
            print(table(summary))
            v = summary["verdict"]
            print("calibrated" if v["calibrated"] else "NOT calibrated: " + "; ".join(v["problems"]))
            if args.strict and not v["calibrated"]:
                status = EXIT_NOT_CALIBRATED
        elif args.command == "sweep":
            if args.workers is not None and args.workers < 1:
                raise ValueError(f"sweep: --workers must be >= 1, got {args.workers}")
            folder, rows = run_sweep(args.sweep, scheduler=args.scheduler, workers=args.workers,
                                     max_start_mm=args.max_start_mm)
            failed = [k for k, r in rows.items() if r.get("status") != "finished"]
            print(f"sweep: {len(rows) - len(failed)} of {len(rows)} runs finished; tables in "
                  f"{folder / 'sweep.md'}")
            if failed:
                status = EXIT_ERROR
    except errors as exc:
        print(f"bayesreg: error: {exc}", file=sys.stderr)
        return EXIT_ERROR
    except KeyboardInterrupt as exc:
        detail = str(exc) if isinstance(exc, RunInterrupted) else "interrupted"
        print(f"bayesreg: {detail}", file=sys.stderr)
        return EXIT_INTERRUPTED
    finally:
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)
    return status


def console() -> None:
    """The ``bayesreg`` command: :func:`main`, then exit with its status.  After an interrupt
    the process exits without waiting for chains still running in worker threads
    (:mod:`bayesreg.sampling.chains`: a chunk inside XLA cannot be stopped, and at a large
    mesh it runs for minutes); the run's files are already written and its directory
    released by then."""
    status = main()
    if status == EXIT_INTERRUPTED:
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(status)
    sys.exit(status)


if __name__ == "__main__":  # pragma: no cover
    console()

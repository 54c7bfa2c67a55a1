"""Command line: ``bayesreg run CONFIG [--out DIR] [--set key=value ...] [--overwrite]``."""

from __future__ import annotations

import argparse
import sys

__all__ = ["main"]


def _parser():
    p = argparse.ArgumentParser(prog="bayesreg", description="Bayesian biomechanical registration")
    sub = p.add_subparsers(dest="command", required=True)
    r = sub.add_parser("run", help="run a YAML config end to end")
    r.add_argument("config", help="YAML config file")
    r.add_argument("--out", help="run directory (default: output.dir of the config)")
    r.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="override a config value, e.g. --set sampler.max_draws=500 (repeatable)")
    r.add_argument("--overwrite", action="store_true", help="replace an existing run directory")
    r.add_argument("--no-progress", action="store_true", help="no progress bar")
    return p


def main(argv=None) -> int:
    args = _parser().parse_args(argv)
    from bayesreg.config import ConfigError

    if args.command == "run":
        from bayesreg.outputs import format_report
        from bayesreg.pipeline import run

        try:
            res = run(args.config, out=args.out, overrides=args.set,
                      overwrite=True if args.overwrite else None,
                      progress=False if args.no_progress else None)
        except (ConfigError, FileExistsError, FileNotFoundError, ValueError) as exc:
            print(f"bayesreg: error: {exc}", file=sys.stderr)
            return 2
        print(format_report(res.errors, res.info))
        t = res.info["timings_s"]
        print(f"wall time before outputs {t.get('total_before_outputs_s', float('nan')):.1f} s; "
              f"outputs in {res.dir}")
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())

"""A finished run as Python sees it: :class:`RunResult`, what :func:`bayesreg.run` returns,
and :func:`open_run`, the same read back from a run directory."""

from __future__ import annotations

from pathlib import Path
from typing import NamedTuple

__all__ = ["RunResult", "open_run"]


class RunResult(NamedTuple):
    """What :func:`bayesreg.run` returns.

    Attributes
    ----------
    dir : Path
        the run directory
    posterior : DataTree
        ArviZ posterior and sample stats
    summary : pandas.DataFrame
    errors : dict or None
        error table (synthetic truth)
    info : dict
        content of ``run.json``
    """

    dir: Path
    posterior: object
    summary: object
    errors: dict | None
    info: dict


def open_run(path) -> RunResult:
    """Open a finished run directory as the :class:`RunResult` that :func:`bayesreg.run`
    returned when it wrote it (a notebook reopening yesterday's run).

    Parameters
    ----------
    path : str or Path
        A run directory with ``run.json``, ``posterior.nc`` and ``summary.csv`` (written by
        :func:`write_outputs`; ``errors.json`` where the run had a truth).

    Returns
    -------
    RunResult
        ``posterior`` read into memory (the file is closed), ``summary`` indexed by
        estimand as written, ``errors`` ``None`` where the run had no truth.

    Raises
    ------
    FileNotFoundError
        If ``path`` is not a directory, or a file above is missing (a run still going or
        interrupted: ``bayesreg run --resume`` finishes it); the message names the file.

    Examples
    --------
    >>> import bayesreg
    >>> result = bayesreg.open_run("runs/quickstart")  # doctest: +SKIP
    >>> result.summary.loc["ratio[gm]", ["eti90_lb", "eti90_ub"]]  # doctest: +SKIP
    """
    import json

    import arviz as az
    import pandas as pd

    path = Path(path)
    if not path.is_dir():
        raise FileNotFoundError(f"run directory {path} not found")
    missing = [n for n in ("run.json", "posterior.nc", "summary.csv") if not (path / n).is_file()]
    if missing:
        raise FileNotFoundError(
            f"{', '.join(missing)} not found in {path}: not a finished run (an interrupted one "
            f"finishes with `bayesreg run --resume {path}`)")
    tree = az.from_netcdf(path / "posterior.nc")
    try:
        tree = tree.load()
    finally:
        tree.close()
    errors_file = path / "errors.json"
    errors = json.loads(errors_file.read_text()) if errors_file.is_file() else None
    return RunResult(path, tree, pd.read_csv(path / "summary.csv", index_col=0), errors,
                     json.loads((path / "run.json").read_text()))

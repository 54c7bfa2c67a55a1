"""JAX/XLA process settings, applied when :mod:`bayesreg` is imported.

* ``jax_enable_x64``: the interior FE solve runs in float64 (float32 CG floors near a
  relative error of 4e-7, see ``FINDINGS.md``), so the whole log-density is float64.
* ``--xla_cpu_experimental_ynn_fusion_type=`` (empty): XLA's CPU backend otherwise fuses
  gather-then-sum (trilinear interpolation, ELL mat-vecs) into kernels measured 4-8x
  slower on these machines (the paper-size log-density with one CG iteration, one core:
  0.73 ms with the flag, 2.28 ms without).  Only added when the user has not set XLA_FLAGS to
  something mentioning it.  XLA reads ``XLA_FLAGS`` once, when JAX starts its first
  backend (the first computation, or ``jax.devices()``), not at ``import jax``: so the
  flag is added whenever no backend has started yet, even if JAX (or a package that
  imports it, such as ArviZ) was imported before :mod:`bayesreg`.  Where a CPU backend
  has already started without it, a :class:`UserWarning` says so (once per process):
  import :mod:`bayesreg` before running any JAX computation, or set the flag in the
  environment.
* OpenBLAS (under NumPy, SciPy and JAX's LAPACK calls such as the Cholesky factorisation
  of the condensed kernel) is limited to one thread: its threads spin against XLA's own
  thread pools, and a 1422 x 1422 Cholesky took 0.5-1.5 s instead of
  35-50 ms on a 2-core machine.  Set through ``OPENBLAS_NUM_THREADS`` when NumPy is not yet
  loaded, else with ``threadpoolctl``; a user's own ``OPENBLAS_NUM_THREADS`` is kept.
"""

from __future__ import annotations

import os
import sys
import warnings

_YNN_FLAG = "--xla_cpu_experimental_ynn_fusion_type="
_FLAG_NAME = "xla_cpu_experimental_ynn_fusion_type"
_warned = False


def _limit_blas() -> None:
    if "OPENBLAS_NUM_THREADS" in os.environ:
        return  # the user's (or an earlier call's) choice
    if "numpy" not in sys.modules:
        os.environ["OPENBLAS_NUM_THREADS"] = "1"
        return
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:  # pragma: no cover - threadpoolctl is a dependency
        return
    threadpool_limits(limits=1, user_api="blas")
    os.environ["OPENBLAS_NUM_THREADS"] = "1"  # for child processes, and to do this once


def _backend_started() -> bool:
    """Whether JAX has started a backend (and so has read ``XLA_FLAGS`` already)."""
    if "jax" not in sys.modules:
        return False
    try:
        from jax._src import xla_bridge
        return bool(xla_bridge.backends_are_initialized())
    except (ImportError, AttributeError):  # pragma: no cover - a JAX without this private API
        return True  # cannot tell: leave XLA_FLAGS alone


def _warn_started_without_flag() -> None:
    """Warn once if a CPU backend started with no setting of the fusion flag."""
    global _warned
    if _warned:
        return
    import jax

    if jax.default_backend() != "cpu":
        return  # the flag only concerns XLA:CPU
    _warned = True
    warnings.warn(
        "JAX's CPU backend was started before bayesreg was imported, without XLA_FLAGS="
        f"{_YNN_FLAG} (XLA reads its flags once, at the first JAX computation): the "
        "log-density runs about 3x slower on this CPU (the image interpolation and the FE "
        "mat-vecs).  Import bayesreg before running any JAX computation (importing jax or "
        "arviz first is fine), or set the flag in the environment, e.g. "
        f"`export XLA_FLAGS={_YNN_FLAG}`, and restart the process.",
        UserWarning,
        # attributed to the user's ``import bayesreg`` line: bayesreg's own frames are
        # skipped, and Python skips the import machinery's
        skip_file_prefixes=(os.path.dirname(os.path.abspath(__file__)) + os.sep,))


def configure() -> None:
    """Apply the settings above (idempotent; every :mod:`bayesreg` module calls it first)."""
    _limit_blas()
    flags = os.environ.get("XLA_FLAGS", "")
    if _FLAG_NAME not in flags:
        if not _backend_started():
            os.environ["XLA_FLAGS"] = (flags + " " + _YNN_FLAG).strip()
        else:
            _warn_started_without_flag()
    import jax

    jax.config.update("jax_enable_x64", True)

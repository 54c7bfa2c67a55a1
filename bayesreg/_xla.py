"""JAX/XLA process settings applied once, before :mod:`jax` is first imported.

* ``jax_enable_x64``: the interior FE solve runs in float64 (float32 CG floors near a
  relative error of 4e-7, see ``FINDINGS.md``), so the whole log-density is float64.
* ``--xla_cpu_experimental_ynn_fusion_type=`` (empty): XLA's CPU backend otherwise fuses
  gather-then-sum (trilinear interpolation, ELL mat-vecs) into kernels measured 4-8x
  slower on these machines.  Only added when the user has not set XLA_FLAGS to
  something mentioning it, and only if JAX has not been imported yet (the flag is read
  once at backend start-up).
* OpenBLAS (under NumPy, SciPy and JAX's LAPACK calls such as the Cholesky factorisation
  of the condensed kernel) is limited to one thread: its threads spin against XLA's own
  thread pools, and a 1422 x 1422 Cholesky took 0.5-1.5 s instead of
  35-50 ms on a 2-core machine.  Set through ``OPENBLAS_NUM_THREADS`` when NumPy is not yet
  loaded, else with ``threadpoolctl``; a user's own ``OPENBLAS_NUM_THREADS`` is kept.
"""

from __future__ import annotations

import os
import sys

_YNN_FLAG = "--xla_cpu_experimental_ynn_fusion_type="


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


def configure() -> None:
    _limit_blas()
    if "jax" not in sys.modules:
        flags = os.environ.get("XLA_FLAGS", "")
        if "xla_cpu_experimental_ynn_fusion_type" not in flags:
            flags = (flags + " " + _YNN_FLAG).strip()
        os.environ["XLA_FLAGS"] = flags
    import jax

    jax.config.update("jax_enable_x64", True)

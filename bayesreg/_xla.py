"""JAX/XLA process settings applied once, before :mod:`jax` is first imported.

* ``jax_enable_x64``: the interior FE solve runs in float64 (float32 CG floors near a
  relative error of 4e-7, see ``FINDINGS.md``), so the whole log-density is float64.
* ``--xla_cpu_experimental_ynn_fusion_type=`` (empty): XLA's CPU backend otherwise fuses
  gather-then-sum (trilinear interpolation, ELL mat-vecs) into kernels measured 4-8x
  slower on these machines.  Only added when the user has not set XLA_FLAGS to
  something mentioning it, and only if JAX has not been imported yet (the flag is read
  once at backend start-up).
* ``--xla_force_host_platform_device_count=N``: the CPU is split into ``N`` host devices
  (default ``max(4, cores)``, or ``BAYESREG_HOST_DEVICES``) so that chains run on separate
  devices (:func:`bayesreg.sampler.sample` shards them) instead of in one vmapped batch:
  vmapped chains whose CG solve is a ``while_loop`` wait for the slowest chain at every
  iteration (3 chains on 2 cores at paper size: 35 steps/s per chain vmapped, 59 sharded
  over 3 devices).  Computations that are not sharded run on device 0 at full speed.  A GPU
  backend is unaffected (one device: chains are vmapped, which is what a GPU wants).
* OpenBLAS (under NumPy, SciPy and JAX's LAPACK calls such as the Cholesky factorisation
  of the condensed kernel) is limited to one thread: its threads spin against XLA's own
  thread pools and the host devices, and a 1422 x 1422 Cholesky took 0.5-1.5 s instead of
  35-50 ms on a 2-core machine.  Set through ``OPENBLAS_NUM_THREADS`` when NumPy is not yet
  loaded, else with ``threadpoolctl``; a user's own ``OPENBLAS_NUM_THREADS`` is kept.
"""

from __future__ import annotations

import os
import sys

_YNN_FLAG = "--xla_cpu_experimental_ynn_fusion_type="


def host_devices() -> int:
    """Number of host (CPU) devices to request: ``BAYESREG_HOST_DEVICES`` or ``max(4, cores)``."""
    env = os.environ.get("BAYESREG_HOST_DEVICES")
    if env:
        return max(1, int(env))
    try:
        cores = len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover - not Linux
        cores = os.cpu_count() or 1
    return max(4, cores)


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
        if "xla_force_host_platform_device_count" not in flags:
            flags = f"{flags} --xla_force_host_platform_device_count={host_devices()}".strip()
        os.environ["XLA_FLAGS"] = flags
    import jax

    jax.config.update("jax_enable_x64", True)

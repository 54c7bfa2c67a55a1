"""Process settings for JAX, applied only when asked: :func:`configure_jax`.

Importing :mod:`bayesreg` changes nothing in the process.  The CLI and :func:`bayesreg.run`
call :func:`configure_jax`; a notebook or script that uses the lower-level modules calls it
first, as NumPyro asks for ``numpyro.enable_x64()``::

    import bayesreg
    bayesreg.configure_jax()

It sets:

* ``jax_enable_x64``: the interior FE solve runs in float64 (a float32 CG stalls near a
  relative residual of 4e-7, far above the solver's tolerance), so the whole log-density is
  float64.  The functions that build float64 state (:func:`bayesreg.model.posterior.build_posterior`,
  the samplers) refuse to run without it (:func:`require_x64`), rather than compute in
  float32 silently.
* ``--xla_cpu_experimental_ynn_fusion_type=`` (empty) in ``XLA_FLAGS``: XLA's CPU backend
  otherwise fuses gather-then-sum (the trilinear interpolation, the ELL mat-vecs) into
  kernels several times slower.  Added only when ``XLA_FLAGS`` does not mention it already.
  XLA reads the flags once, when JAX starts its first backend, so the call must come
  before the first JAX computation; a CPU backend already started without it gets a
  :class:`UserWarning`.
* OpenBLAS (under NumPy, SciPy and JAX's LAPACK calls) limited to one thread: its threads
  spin against XLA's own thread pools and slow the dense factorisations by an order of
  magnitude on a few cores.  Through ``OPENBLAS_NUM_THREADS`` when NumPy is not loaded
  yet, else ``threadpoolctl``; a user's own ``OPENBLAS_NUM_THREADS`` is kept.
"""

from __future__ import annotations

import os
import sys
import warnings

__all__ = ["configure_jax", "require_x64"]

_YNN_FLAG = "--xla_cpu_experimental_ynn_fusion_type="
_FLAG_NAME = "xla_cpu_experimental_ynn_fusion_type"
_warned = False


def _limit_blas() -> None:
    if "OPENBLAS_NUM_THREADS" in os.environ:
        return  # the user's (or an earlier call's) choice
    if "numpy" not in sys.modules:
        os.environ["OPENBLAS_NUM_THREADS"] = "1"
        return
    from threadpoolctl import threadpool_limits

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
        "JAX's CPU backend was started before bayesreg.configure_jax(), without XLA_FLAGS="
        f"{_YNN_FLAG} (XLA reads its flags once, at the first JAX computation): the "
        "log-density runs about 3x slower on this CPU (the image interpolation and the FE "
        "mat-vecs).  Call bayesreg.configure_jax() before running any JAX computation, or "
        f"set the flag in the environment, e.g. `export XLA_FLAGS={_YNN_FLAG}`, and restart "
        "the process.",
        UserWarning, stacklevel=3)


def configure_jax() -> None:
    """Apply bayesreg's JAX settings to this process (see the module docstring).

    Idempotent.  Call it before the first JAX computation of the process; the CLI and
    :func:`bayesreg.run` call it themselves.

    Warns
    -----
    UserWarning
        JAX's CPU backend had started before the first call, without the XLA flag (the
        computations stay correct, only slower).

    Examples
    --------
    >>> import jax
    >>> import bayesreg
    >>> bayesreg.configure_jax()
    >>> jax.numpy.zeros(2).dtype
    dtype('float64')
    """
    _limit_blas()
    flags = os.environ.get("XLA_FLAGS", "")
    if _FLAG_NAME not in flags:
        if not _backend_started():
            os.environ["XLA_FLAGS"] = (flags + " " + _YNN_FLAG).strip()
        else:
            _warn_started_without_flag()
    import jax

    jax.config.update("jax_enable_x64", True)


def require_x64(stage: str) -> None:
    """Raise unless JAX runs in float64 (:func:`configure_jax`, or ``jax_enable_x64``).

    Parameters
    ----------
    stage : str
        What needs it, for the message (e.g. ``"build_posterior"``).

    Raises
    ------
    RuntimeError
        ``jax_enable_x64`` is off: arrays would silently be float32 and the CG solve would
        not reach its tolerance.
    """
    import jax

    if not jax.config.jax_enable_x64:
        raise RuntimeError(
            f"{stage}: JAX runs in float32 (jax_enable_x64 is off), and bayesreg's FE solve "
            "needs float64: call bayesreg.configure_jax() at the start of the process "
            "(the CLI and bayesreg.run do it themselves)")

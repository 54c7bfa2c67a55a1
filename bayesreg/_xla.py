"""JAX/XLA process settings applied once, before :mod:`jax` is first imported.

* ``jax_enable_x64``: the interior FE solve runs in float64 (float32 CG floors near a
  relative error of 4e-7, see ``FINDINGS.md``), so the whole log-density is float64.
* ``--xla_cpu_experimental_ynn_fusion_type=`` (empty): XLA's CPU backend otherwise fuses
  gather-then-sum (trilinear interpolation, ELL mat-vecs) into kernels measured 4-8x
  slower on these machines.  Only added when the user has not set XLA_FLAGS to
  something mentioning it, and only if JAX has not been imported yet (the flag is read
  once at backend start-up).
"""

from __future__ import annotations

import os
import sys

_YNN_FLAG = "--xla_cpu_experimental_ynn_fusion_type="


def configure() -> None:
    if "jax" not in sys.modules:
        flags = os.environ.get("XLA_FLAGS", "")
        if "xla_cpu_experimental_ynn_fusion_type" not in flags:
            os.environ["XLA_FLAGS"] = (flags + " " + _YNN_FLAG).strip()
    import jax

    jax.config.update("jax_enable_x64", True)

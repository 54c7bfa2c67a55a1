"""A/B of the preconditioner's storage in ``benchmarks/steps.py``: packed (the CPU default),
dense, or row blocks (the dense inverse as ``(8, b, 8 b)``, one batched product).

Usage, from the repository root: ``python benchmarks/results/cpu-stop41/storage_steps.py
MODE [steps.py options]``, MODE one of ``packed``, ``dense``, ``rowblk``.  A patch of the
library for a measurement (stop 41), not library code."""
import sys
mode = sys.argv.pop(1)
from pathlib import Path
sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # benchmarks/, for steps.py
import bayesreg.solver as S
import jax, jax.numpy as jnp
if mode == "dense":
    S.PACKED_BLOCK_ROWS = 1
elif mode == "rowblk":
    R = 8
    orig_build = S.dense_preconditioner
    def build(op, b_ii, *, block_rows=None):
        p = orig_build(op, b_ii, block_rows=1)
        n = p.inverse.shape[0]; b = -(-n // R)
        m = jnp.pad(p.inverse, ((0, R * b - n), (0, R * b - n))).reshape(R, b, R * b)
        return S.DensePreconditioner(m, p.fallback)
    S.dense_preconditioner = build
    import bayesreg.posterior as P
    P.dense_preconditioner = build  # posterior.py imports it by name
    orig_apply = S.DensePreconditioner.apply
    def apply(self, r):
        if self.inverse.ndim == 3 and self.inverse.shape[2] != self.inverse.shape[1]:
            x = r.reshape(-1).astype(jnp.float32)
            nb = self.inverse.shape[2]
            x = jnp.pad(x, (0, nb - x.size))
            y = jax.lax.dot_general(self.inverse, x, (((2,), (0,)), ((), ())))
            return y.reshape(-1)[:r.size].astype(r.dtype).reshape(r.shape)
        return orig_apply(self, r)
    S.DensePreconditioner.apply = apply
import steps
steps.main()

"""Experiment (stop 40): the dense K_ii^-1 stored in float16, unit-diagonal form, applied
as a float16 x float16 -> float32 product on a normalised residual.  Patches
bayesreg.solver, then runs benchmarks/steps.py with the given arguments.  F16=0: as shipped."""
import os, sys
sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "..", "..", "benchmarks"))  # from benchmarks/results/gpu-h200-stop40/
import steps  # configures XLA
import jax, jax.numpy as jnp
from bayesreg import solver as S

if os.environ.get("F16", "1") == "1":
    _build = S.dense_preconditioner

    def dense_preconditioner(op, b_ii, *, block_rows=None):
        pre = _build(op, b_ii, block_rows=1)
        diag = jax.lax.stop_gradient(S.ell_diagonal(b_ii, op.row_ii))
        d = (1.0 / jnp.sqrt(jnp.abs(jnp.diagonal(diag, axis1=1, axis2=2)))).reshape(-1).astype(jnp.float32)
        s = pre.inverse / (d[:, None] * d[None, :])
        return S.DensePreconditioner((s.astype(jnp.float16), d), pre.fallback)

    def apply(self, r):
        s16, d = self.inverse
        x = r.reshape(-1).astype(jnp.float32) * d
        scale = jnp.maximum(jnp.max(jnp.abs(x)), jnp.finfo(jnp.float32).tiny)
        y = jnp.dot(s16, (x / scale).astype(jnp.float16), preferred_element_type=jnp.float32)
        return (y * d * scale).astype(r.dtype).reshape(r.shape)

    S.dense_preconditioner = dense_preconditioner
    import bayesreg.posterior as P
    P.dense_preconditioner = dense_preconditioner
    S.DensePreconditioner.apply = apply
    print("float16 preconditioner", flush=True)
steps.main(sys.argv[1:])

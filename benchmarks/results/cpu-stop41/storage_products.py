"""Products with a 1,374-DOF float32 SPD matrix stored three ways: dense, packed (the
library's CPU form, ``bayesreg.solver.pack_symmetric``) and in 8 row blocks.

Usage: ``python benchmarks/results/cpu-stop41/storage_products.py THREADS``; each of THREADS
host threads runs a jitted loop of 400 products with its own copy of the matrix, and the
script prints the wall time per product, 7 rounds (the first one warms up).  Stop 41."""
import sys, time, threading
from bayesreg import _xla
_xla.configure()
import jax, jax.numpy as jnp, numpy as np
from bayesreg.solver import pack_symmetric, DensePreconditioner
jax.config.update("jax_enable_x64", True)
n = 1374
rng = np.random.default_rng(0)
A = rng.standard_normal((n, n)).astype(np.float32); A = (A @ A.T / n + np.eye(n)).astype(np.float32)
packed = DensePreconditioner(jnp.asarray(pack_symmetric(A, 8)), jnp.asarray(False))
dense = DensePreconditioner(jnp.asarray(A), jnp.asarray(False))
R = 8; b = -(-n // R)
Ab = np.zeros((R * b, R * b), np.float32); Ab[:n, :n] = A
rowblk = jnp.asarray(Ab.reshape(R, b, R * b))
def apply_rowblk(M, r):
    x = jnp.pad(r.reshape(-1).astype(jnp.float32), (0, R * b - r.size))
    y = jax.lax.dot_general(M, x, (((2,), (0,)), ((), ())))
    return y.reshape(-1)[:r.size].astype(r.dtype).reshape(r.shape)
K = 400
def loop(f):
    @jax.jit
    def run(M, r):
        def body(i, r):
            y = f(M, r)
            return r + 1e-6 * y
        return jax.lax.fori_loop(0, K, body, r)
    return run
r0 = jnp.asarray(rng.standard_normal((n // 3, 3)))
variants = {
  "dense": (loop(lambda M, r: M.apply(r)), dense),
  "packed": (loop(lambda M, r: M.apply(r)), packed),
  "rowblk": (loop(apply_rowblk), rowblk),
}
# check equality
print("rowblk vs dense", float(jnp.max(jnp.abs(apply_rowblk(rowblk, r0) - dense.apply(r0)))))
for name, (f, M) in variants.items():
    f(M, r0).block_until_ready()
nthreads = int(sys.argv[1]) if len(sys.argv) > 1 else 1
for rnd in range(7):
    for name, (f, M) in variants.items():
        Ms = [jax.tree.map(lambda a: a + 0, M) for _ in range(nthreads)]
        def work(i):
            f(Ms[i], r0).block_until_ready()
        t = time.perf_counter()
        th = [threading.Thread(target=work, args=(i,)) for i in range(nthreads)]
        [x.start() for x in th]; [x.join() for x in th]
        dt = time.perf_counter() - t
        print(f"round {rnd} {name:7s} threads {nthreads}: {dt / K * 1e6:7.1f} us per product (wall, each thread)")

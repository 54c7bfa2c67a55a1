"""Can the dense preconditioner ``K_ii^-1`` be stored compressed?  (not part of the test suite)

The random walk's CG applies each chain's float32 ``K_ii^-1`` (README, "Dense
preconditioner") 3-4 times per proposal, and that product streams the whole matrix (8 MB at
the paper's size).  The inverse of an elliptic operator is often *hierarchically* low-rank:
with the DOFs ordered by recursive coordinate bisection, the off-diagonal blocks of a HODLR
matrix (Hackbusch 1999; Ambikasaran & Darve 2013) are truncated SVDs, and a product costs
the stored entries.  This script measures, on a run's problem, how many entries such a
compression keeps at each truncation and what it costs in CG iterations, with the
sampler's CG (float64, relative residual 1e-8, float32 preconditioner, warm start from the
chain's interior)::

    python benchmarks/inverse_rank.py --problem RUN/checkpoint/problem.npz \
        --posterior RUN/posterior.nc [--time 1e-3]

Each of ``--proposals`` cases is one proposal of the paper's joint kernel (``--sigma``: the
paper configs' steps of ``lam``, ``mu`` and ``u_b``) from a chain's state.  With
``--posterior RUN/posterior.nc`` the states are the run's own draws, in 4 random chunks,
and the preconditioner is built where the sampler builds it, at the chunk's start;
without it, random walks of up to 500 steps from ``--lam``, ``--mu`` at the truth's
boundary.  The script also says where the CG iterations come from: the same proposals
preconditioned at the chain's current parameters, at those with the proposal's CSF
parameters, at the proposal's own (exact), and a proposal that moves ``u_b`` only.  Dense
NumPy/SciPy, one process, a minute or two at the paper's size.

``--time EPS`` also times, in JAX on this machine, a product with the float32 dense inverse
against one with the HODLR form truncated at ``EPS`` of each block (ranks padded to each
level's largest, the leaves padded to one size, gathers in and out), in a jitted loop of
2,000 products: one thread alone, and three threads with three chains' matrices at once (the
sampler's three chains on two cores).
"""

from __future__ import annotations

import argparse

import numpy as np

from bayesreg import fem
from bayesreg.labels import TISSUES


def _floats(text, n, name):
    v = [float(x) for x in text.split(",")]
    if len(v) != n:
        raise SystemExit(f"--{name} takes {n} comma-separated values, got {text!r}")
    return np.array(v)


def _bisection_order(points, levels):
    """Recursive coordinate bisection: ``2**levels`` parts of equal size, in order."""
    def split(idx, depth):
        if depth == 0:
            return [idx]
        x = points[idx]
        axis = int(np.argmax(np.ptp(x, axis=0)))
        order = idx[np.argsort(x[:, axis], kind="stable")]
        h = len(order) // 2
        return split(order[:h], depth - 1) + split(order[h:], depth - 1)
    return split(np.arange(len(points)), levels)


def hodlr(a, offsets, eps, scale):
    """HODLR approximation of ``a`` (dense leaves, off-diagonal blocks truncated).

    Singular values below ``eps * scale(block)`` are dropped; returns the approximation,
    the number of stored entries, the ranks of the first level's blocks and the largest
    rank of each level.
    """
    out = np.zeros_like(a)
    stored, top, ranks = 0, [], {}
    leaves = len(offsets) - 1

    def rec(lo, hi, level):
        nonlocal stored
        r = slice(offsets[lo], offsets[hi])
        if hi - lo == 1:
            out[r, r] = a[r, r]
            stored += (offsets[hi] - offsets[lo]) ** 2
            return
        mid = (lo + hi) // 2
        for r0, r1, c0, c1 in ((lo, mid, mid, hi), (mid, hi, lo, mid)):
            rs, cs = slice(offsets[r0], offsets[r1]), slice(offsets[c0], offsets[c1])
            u, s, vt = np.linalg.svd(a[rs, cs], full_matrices=False)
            k = int(np.sum(s > eps * scale(s)))
            out[rs, cs] = (u[:, :k] * s[:k]) @ vt[:k]
            stored += k * (sum(a[rs, cs].shape))
            ranks[level] = max(ranks.get(level, 0), k)
            if level == 0:
                top.append(k)
        rec(lo, mid, level + 1)
        rec(mid, hi, level + 1)

    rec(0, leaves, 0)
    return out, stored, top, [ranks[i] for i in sorted(ranks)]


def _padded_factors(inv_p, sizes, ranks):
    """The HODLR form of ``inv_p`` as padded float32 arrays for a batched JAX product."""
    levels = len(ranks)
    offsets = np.r_[0, np.cumsum(sizes)]
    s = max(sizes)
    pos = np.concatenate([j * s + np.arange(m) for j, m in enumerate(sizes)])
    leaves = np.zeros((len(sizes), s, s), np.float32)
    for j, m in enumerate(sizes):
        leaves[j, :m, :m] = inv_p[offsets[j]:offsets[j + 1], offsets[j]:offsets[j + 1]]
    factors = []
    for level, k in enumerate(ranks):
        nb, w = 2 ** level, 2 ** (levels - level)
        u_f = np.zeros((nb, 2, w // 2 * s, k), np.float32)
        v_f = np.zeros_like(u_f)
        for b in range(nb):
            lo, mid, hi = b * w, b * w + w // 2, (b + 1) * w
            for t, (r0, r1, c0, c1) in enumerate(((lo, mid, mid, hi), (mid, hi, lo, mid))):
                blk = inv_p[offsets[r0]:offsets[r1], offsets[c0]:offsets[c1]]
                u, sv, vt = np.linalg.svd(blk, full_matrices=False)
                u_f[b, t][pos[offsets[r0]:offsets[r1]] - r0 * s] = u[:, :k] * sv[:k]
                v_f[b, t][pos[offsets[c0]:offsets[c1]] - c0 * s] = vt[:k].T
        factors.append((u_f, v_f))
    return pos, leaves, factors


def time_products(invs, perm, sizes, ranks, n_products=2000):
    """Microseconds per product: dense float32 against HODLR, 1 thread and 3 at once."""
    import threading
    import time

    from bayesreg import _xla

    _xla.configure()
    import jax
    import jax.numpy as jnp

    n = len(perm)
    forms = [_padded_factors(inv[np.ix_(perm, perm)], sizes, ranks) for inv in invs]
    pos = forms[0][0]
    g_in = np.full(len(sizes) * max(sizes), n)
    g_in[pos] = perm
    g_out = np.empty(n, int)
    g_out[perm] = pos
    g_in, g_out = jnp.asarray(g_in), jnp.asarray(g_out)

    def hodlr_apply(leaves, factors, x):
        xp = jnp.concatenate([x.astype(jnp.float32), jnp.zeros(1, jnp.float32)])[g_in]
        y = jnp.einsum("jab,jb->ja", leaves, xp.reshape(leaves.shape[0], -1)).reshape(-1)
        for u_f, v_f in factors:
            xb = xp.reshape(u_f.shape[0], 2, -1)
            c0 = jnp.einsum("bak,ba->bk", v_f[:, 0], xb[:, 1])
            c1 = jnp.einsum("bak,ba->bk", v_f[:, 1], xb[:, 0])
            y = y + jnp.stack([jnp.einsum("bak,bk->ba", u_f[:, 0], c0),
                               jnp.einsum("bak,bk->ba", u_f[:, 1], c1)], 1).reshape(-1)
        return y[g_out].astype(x.dtype)

    def loop(apply):
        return jax.jit(lambda x: jax.lax.fori_loop(
            0, n_products, lambda i, x: 0.5 * x + 1e-3 * apply(x), x))

    x = jnp.asarray(np.random.default_rng(0).normal(size=n))
    rows = []
    for name in ("dense", "HODLR", "dense", "HODLR"):
        if name == "dense":
            runs = [loop(lambda x, m=jnp.asarray(inv, jnp.float32):
                         (m @ x.astype(jnp.float32)).astype(x.dtype)) for inv in invs]
        else:
            runs = [loop(lambda x, lv=jnp.asarray(f[1]), fs=jax.tree.map(jnp.asarray, f[2]):
                         hodlr_apply(lv, fs, x)) for f in forms]
        for r in runs:
            r(x).block_until_ready()
        t = time.perf_counter()
        runs[0](x).block_until_ready()
        one = (time.perf_counter() - t) / n_products * 1e6
        threads = [threading.Thread(target=lambda r=r: r(x).block_until_ready()) for r in runs]
        t = time.perf_counter()
        for th in threads:
            th.start()
        for th in threads:
            th.join()
        three = (time.perf_counter() - t) / n_products / len(runs) * 1e6
        rows.append((name, one, three))
    return rows


def pcg_iterations(a, b, x0, m, rtol=1e-8, maxiter=500):
    """Iterations of preconditioned CG (as ``bayesreg.solver.pcg``) to ``rtol``."""
    x = x0.copy()
    r = b - a @ x
    bn = np.linalg.norm(b)
    if np.linalg.norm(r) <= rtol * bn:
        return 0
    z = m @ r
    p, rz = z.copy(), r @ z
    for it in range(1, maxiter + 1):
        ap = a @ p
        alpha = rz / (p @ ap)
        x += alpha * p
        r -= alpha * ap
        if np.linalg.norm(r) <= rtol * bn:
            return it
        z = m @ r
        rz_new = r @ z
        p = z + (rz_new / rz) * p
        rz = rz_new
    return maxiter


def _chain_states(path, boundary, chunk_draws, n_refs, per_ref, rng):
    """Chunk starts and later states of a run's chains, from its ``posterior.nc``.

    Returns ``[(theta_0, [(theta, u_b), ...]), ...]``: ``n_refs`` random (chain, chunk)
    pairs, ``theta_0 = (lam, mu)`` at the chunk's start (the last draw of the chunk before,
    where the sampler builds the preconditioner) and ``per_ref`` states at random draws
    within the chunk.
    """
    import xarray as xr

    ds = xr.open_dataset(path, group="posterior")
    if "group" not in ds.dims or [str(g) for g in ds["group"].values] != list(TISSUES):
        raise SystemExit(f"{path}: not a run of per-tissue parameters {TISSUES} (the uniform "
                         "model's spectral preconditioner is exact at every lam, mu)")
    node = ds["node"].values
    if not np.array_equal(np.sort(node), np.sort(boundary)):
        raise SystemExit(f"{path}: its boundary nodes are not the problem's")
    order = np.argsort(node)[np.argsort(np.argsort(boundary))]
    n_chains, n_draws = ds.sizes["chain"], ds.sizes["draw"]
    n_chunks = n_draws // chunk_draws
    if n_chunks < 2:
        raise SystemExit(f"{path}: {n_draws} draws hold fewer than 2 chunks of {chunk_draws}")
    out = []
    for _ in range(n_refs):
        c, k = int(rng.integers(n_chains)), int(rng.integers(1, n_chunks))
        start = k * chunk_draws - 1

        def theta(d):
            return np.r_[ds["lam"][c, d].values, ds["mu"][c, d].values]

        states = [(theta(d), ds["u_b"][c, d].values[order].ravel())
                  for d in start + rng.integers(0, chunk_draws, size=per_ref)]
        out.append((theta(start), states))
    return out


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--problem", required=True, help="a run's checkpoint/problem.npz")
    p.add_argument("--posterior", help="the same run's posterior.nc: take the chains' states "
                   "and their chunk-start parameters from its draws (instead of random walks "
                   "from --lam, --mu around the truth)")
    p.add_argument("--chunk-draws", type=int, default=100,
                   help="stored draws per chunk of that run (the paper configs': 1,000 steps, "
                   "thinning 10)")
    p.add_argument("--lam", default="3.8,9.5,26", help="lam of (CSF, GM, WM) at the "
                   "preconditioner (default: near the paper run's posterior)")
    p.add_argument("--mu", default="0.17,1,1.03", help="mu of (CSF, GM, WM)")
    p.add_argument("--sigma", default="0.1,0.01,0.008",
                   help="proposal steps of lam, mu, u_b (mm)")
    p.add_argument("--levels", type=int, default=3, help="bisection levels (2**levels leaves)")
    p.add_argument("--proposals", type=int, default=40)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--time", type=float, metavar="EPS",
                   help="also time products with the inverse dense and HODLR-truncated at EPS")
    args = p.parse_args(argv)

    z = np.load(args.problem)
    nodes, tets, tissue, boundary = z["nodes"], z["tets"], z["tissue"], z["boundary"]
    lam0 = _floats(args.lam, len(TISSUES), "lam")
    mu0 = _floats(args.mu, len(TISSUES), "mu")
    s_lam, s_mu, s_u = _floats(args.sigma, 3, "sigma")
    free = np.r_[True, True, True, True, False, True]  # mu_GM fixed (paper Sec. 3.3)
    step = np.r_[np.full(3, s_lam), np.full(3, s_mu)] * free

    interior = np.setdiff1d(np.arange(len(nodes)), boundary)
    di = (3 * interior[:, None] + np.arange(3)).ravel()
    db = (3 * boundary[:, None] + np.arange(3)).ravel()

    def blocks(theta):
        k = fem.stiffness_matrix(nodes, tets, theta[:3][tissue], theta[3:][tissue]).tocsr()
        return k[di][:, di], k[di][:, db]

    def inverse(theta):
        return np.linalg.inv(blocks(theta)[0].toarray())

    rng = np.random.default_rng(args.seed)
    if args.posterior:
        n_refs = 4
        refs = _chain_states(args.posterior, boundary, args.chunk_draws, n_refs,
                             -(-args.proposals // n_refs), rng)
        source = f"states of {args.posterior}"
    else:
        if "truth_u" not in z.files:
            raise SystemExit(f"{args.problem} holds no synthetic truth (truth_u): give "
                             "--posterior")
        theta0 = np.r_[lam0, mu0]
        u_b = z["truth_u"][boundary].ravel()
        states = [(np.maximum(theta0 + step * rng.normal(size=6) * np.sqrt(rng.integers(0, 501)),
                              1e-3 * theta0), u_b) for _ in range(args.proposals)]
        refs = [(theta0, states)]
        source = "random walks of up to 500 steps from --lam, --mu, at the truth's u_b"

    # each case: a proposal of the paper's joint kernel from a chain's state, warm-started
    # from the chain's interior (exact at its state, as the sampler's is to 1e-8)
    cases = []
    for r, (theta0, states) in enumerate(refs):
        for theta_c, u_c in states:
            theta_p = np.maximum(theta_c + step * rng.normal(size=6), 1e-6)
            u_p = u_c + s_u * rng.normal(size=u_c.size)
            ki, kb = blocks(theta_c)
            x0 = np.linalg.solve(ki.toarray(), -kb @ u_c)
            kp, kbp = blocks(theta_p)
            csf = theta_c.copy()
            csf[[0, 3]] = theta_p[[0, 3]]
            cases.append(dict(ref=r, a=kp, b=-kbp @ u_p, x0=x0, a_u=ki, b_u=-kb @ u_p,
                              theta_c=theta_c, theta_p=theta_p, theta_csf=csf))

    def f32(a):
        return a.astype(np.float32).astype(np.float64)

    ref_inv = [inverse(theta0) for theta0, _ in refs]
    n = ref_inv[0].shape[0]
    print(f"{args.problem}: {n} interior DOFs, {len(db)} boundary DOFs; {len(cases)} "
          f"proposals from {source}")

    print("\nWhere the CG iterations come from (the preconditioner at ...):\n")
    print("| preconditioner | CG iterations per proposal |\n|---|---|")
    rows = (("the chunk's start (the sampler's)", lambda c: ref_inv[c["ref"]], "a", "b"),
            ("the chain's current parameters", lambda c: inverse(c["theta_c"]), "a", "b"),
            ("the chain's, with the proposal's CSF parameters",
             lambda c: inverse(c["theta_csf"]), "a", "b"),
            ("the proposal's parameters (exact)", lambda c: inverse(c["theta_p"]), "a", "b"),
            ("the chain's current, a proposal moving u_b only",
             lambda c: inverse(c["theta_c"]), "a_u", "b_u"))
    for label, prec, a, b in rows:
        its = np.mean([pcg_iterations(c[a], c[b], c["x0"], f32(prec(c))) for c in cases])
        print(f"| {label} | {its:.2f} |")

    parts = _bisection_order(nodes[interior], args.levels)
    perm = np.concatenate([(3 * q[:, None] + np.arange(3)).ravel() for q in parts])
    back = np.argsort(perm)
    offsets = np.r_[0, np.cumsum([3 * len(q) for q in parts])]
    half = offsets[len(offsets) // 2]
    print(f"\nThe chunk-start inverse compressed (HODLR, {2 ** args.levels} leaves of "
          f"{np.diff(offsets).min()}-{np.diff(offsets).max()} DOFs):\n")
    print("| truncation | stored entries (of dense) | float32 MB | ranks of the two "
          "top blocks (of their size) | CG iterations per proposal |")
    print("|---|---|---|---|---|")
    its = np.mean([pcg_iterations(c["a"], c["b"], c["x0"], f32(ref_inv[c["ref"]])) for c in cases])
    print(f"| none (the sampler's dense inverse) | 1.00 | {n * n * 4 / 1e6:.2f} | | {its:.2f} |")
    inv_p = [inv[np.ix_(perm, perm)] for inv in ref_inv]
    for label, rel in (("of the block", True), ("of the matrix", False)):
        for eps in (1e-4, 1e-3, 1e-2):
            forms = []
            for inv, ip in zip(ref_inv, inv_p):
                g = np.linalg.norm(inv, 2)
                forms.append(hodlr(ip, offsets, eps, (lambda s: s[0]) if rel else (lambda s, g=g: g)))
            ms = [f32(f[0][np.ix_(back, back)]) for f in forms]
            its = np.mean([pcg_iterations(c["a"], c["b"], c["x0"], ms[c["ref"]]) for c in cases])
            stored, top = np.mean([f[1] for f in forms]), forms[0][2]
            print(f"| {eps:g} {label} | {stored / n / n:.2f} | {stored * 4 / 1e6:.2f} | "
                  f"{top[0]}, {top[1]} ({half}) | {its:.2f} |")

    if args.time is not None:
        _, _, _, ranks = hodlr(inv_p[0], offsets, args.time, lambda s: s[0])
        theta0 = refs[0][0]
        invs = (ref_inv + [inverse(theta0 * f) for f in (1.05, 1.1)])[:3]  # three chains'
        rows = time_products(invs, perm, np.diff(offsets), ranks)
        print(f"\nproducts, HODLR at {args.time:g} of each block (ranks per level {ranks}), "
              "us per product:")
        print("| form | 1 thread | 3 threads at once |\n|---|---|---|")
        for name, one, three in rows:
            print(f"| {name} | {one:.0f} | {three:.0f} |")


if __name__ == "__main__":
    main()

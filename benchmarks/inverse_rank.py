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

from bayesreg import _xla

_xla.configure()
import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

from bayesreg import fem, solver  # noqa: E402
from bayesreg.labels import TISSUES  # noqa: E402


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


def _block_tree(n_leaves):
    """Off-diagonal blocks of a HODLR tree, level by level.

    Yields ``(level, b, t, (r0, r1), (c0, c1))`` in leaf units: block ``b`` of the level
    splits leaves ``r0 .. c1`` in halves, ``t = 0`` its upper right, ``t = 1`` its lower left.
    """
    levels = int(np.log2(n_leaves))
    for level in range(levels):
        w = 2 ** (levels - level)
        for b in range(2 ** level):
            lo, mid, hi = b * w, b * w + w // 2, (b + 1) * w
            yield level, b, 0, (lo, mid), (mid, hi)
            yield level, b, 1, (mid, hi), (lo, mid)


def block_svds(a, offsets):
    """SVD of every off-diagonal block of ``a``: ``[(level, b, t, rows, cols, (u, s, vt))]``."""
    out = []
    for level, b, t, (r0, r1), (c0, c1) in _block_tree(len(offsets) - 1):
        rs, cs = slice(offsets[r0], offsets[r1]), slice(offsets[c0], offsets[c1])
        out.append((level, b, t, rs, cs, np.linalg.svd(a[rs, cs], full_matrices=False)))
    return out


def hodlr(a, offsets, svds, eps, scale):
    """HODLR approximation of ``a`` (dense leaves, off-diagonal blocks truncated).

    Singular values below ``eps * scale`` are dropped (``scale=None``: each block's largest);
    returns the approximation, the number of stored entries, the ranks of the first level's
    blocks and the largest rank of each level.
    """
    out = np.zeros_like(a)
    stored, ranks = 0, {}
    for j in range(len(offsets) - 1):
        r = slice(offsets[j], offsets[j + 1])
        out[r, r] = a[r, r]
        stored += (offsets[j + 1] - offsets[j]) ** 2
    top = []
    for level, _, _, rs, cs, (u, s, vt) in svds:
        k = int(np.sum(s > eps * (s[0] if scale is None else scale)))
        out[rs, cs] = (u[:, :k] * s[:k]) @ vt[:k]
        stored += k * (u.shape[0] + vt.shape[1])
        ranks[level] = max(ranks.get(level, 0), k)
        if level == 0:
            top.append(k)
    return out, stored, top, [ranks[i] for i in sorted(ranks)]


def _padded_factors(inv_p, offsets, svds, ranks):
    """The HODLR form of ``inv_p`` as padded float32 arrays for a batched JAX product."""
    sizes = np.diff(offsets)
    s = max(sizes)
    pos = np.concatenate([j * s + np.arange(m) for j, m in enumerate(sizes)])
    leaves = np.zeros((len(sizes), s, s), np.float32)
    for j, m in enumerate(sizes):
        leaves[j, :m, :m] = inv_p[offsets[j]:offsets[j + 1], offsets[j]:offsets[j + 1]]
    levels = len(ranks)
    factors = [(np.zeros((2 ** lv, 2, 2 ** (levels - lv - 1) * s, k), np.float32),
                np.zeros((2 ** lv, 2, 2 ** (levels - lv - 1) * s, k), np.float32))
               for lv, k in enumerate(ranks)]
    for (level, b, t, rs, cs, (u, sv, vt)), (_, _, _, (r0, _), (c0, _)) in zip(
            svds, _block_tree(len(sizes))):
        k = ranks[level]
        u_f, v_f = factors[level]
        u_f[b, t][pos[rs] - r0 * s] = u[:, :k] * sv[:k]
        v_f[b, t][pos[cs] - c0 * s] = vt[:k].T
    return pos, leaves, factors


def time_products(invs, forms, perm, n_products=2000):
    """Microseconds per product: dense float32 against HODLR, 1 thread and 3 at once.

    ``forms`` are the matrices' :func:`_padded_factors` in the bisection order ``perm``.
    """
    import threading
    import time

    n = len(perm)
    pos, leaves = forms[0][0], forms[0][1]
    g_in = np.full(leaves.shape[0] * leaves.shape[1], n)
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


@jax.jit
def _cg_iterations(a, b, x0, m):
    _, info = solver.pcg(lambda v: a @ v, b, x0, lambda r: m @ r, rtol=1e-8, maxiter=500)
    return info.iterations


def cg_iterations(a, b, x0, m):
    """Iterations of the sampler's CG (:func:`bayesreg.solver.pcg`, rtol 1e-8) on dense ``a``
    (sparse or dense), preconditioned by ``m`` rounded to float32 as the sampler stores it."""
    a = a.toarray() if hasattr(a, "toarray") else a
    m32 = np.asarray(m, np.float32).astype(np.float64)
    return int(_cg_iterations(jnp.asarray(a), jnp.asarray(b), jnp.asarray(x0), jnp.asarray(m32)))


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
        k = fem.stiffness_matrix(nodes, tets, theta[:3][tissue], theta[3:][tissue]).tocsr()[di]
        return k[:, di].toarray(), k[:, db]

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

    ref_inv = [np.linalg.inv(blocks(theta0)[0]) for theta0, _ in refs]
    n = ref_inv[0].shape[0]
    print(f"{args.problem}: {n} interior DOFs, {len(db)} boundary DOFs; "
          f"{sum(len(st) for _, st in refs)} proposals from {source}")

    # each case: a proposal of the paper's joint kernel from a chain's state, warm-started
    # from the chain's interior (exact at its state, as the sampler's is to 1e-8), solved
    # with the preconditioner at each of the rows' parameters
    labels = ("the chunk's start (the sampler's)", "the chain's current parameters",
              "the chain's, with the proposal's CSF parameters",
              "the proposal's parameters (exact)",
              "the chain's current, a proposal moving u_b only")
    cases, its = [], []
    for r, (theta0, states) in enumerate(refs):
        for theta_c, u_c in states:
            theta_p = np.maximum(theta_c + step * rng.normal(size=6), 1e-6)
            u_p = u_c + s_u * rng.normal(size=u_c.size)
            k_c, kb_c = blocks(theta_c)
            x0 = np.linalg.solve(k_c, -kb_c @ u_c)
            k_p, kb_p = blocks(theta_p)
            b_p = -kb_p @ u_p
            csf = theta_c.copy()
            csf[[0, 3]] = theta_p[[0, 3]]
            inv_c = np.linalg.inv(k_c)
            its.append([cg_iterations(k_p, b_p, x0, ref_inv[r]),
                        cg_iterations(k_p, b_p, x0, inv_c),
                        cg_iterations(k_p, b_p, x0, np.linalg.inv(blocks(csf)[0])),
                        cg_iterations(k_p, b_p, x0, np.linalg.inv(k_p)),
                        cg_iterations(k_c, -kb_c @ u_p, x0, inv_c)])
            cases.append((r, k_p, b_p, x0))
    its = np.mean(its, axis=0)

    print("\nWhere the CG iterations come from (the preconditioner at ...):\n")
    print("| preconditioner | CG iterations per proposal |\n|---|---|")
    for label, it in zip(labels, its):
        print(f"| {label} | {it:.2f} |")

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
    print(f"| none (the sampler's dense inverse) | 1.00 | {n * n * 4 / 1e6:.2f} | | {its[0]:.2f} |")
    inv_p = [inv[np.ix_(perm, perm)] for inv in ref_inv]
    svds = [block_svds(ip, offsets) for ip in inv_p]
    norms = [np.linalg.norm(inv, 2) for inv in ref_inv]
    for label, rel in (("of the block", True), ("of the matrix", False)):
        for eps in (1e-4, 1e-3, 1e-2):
            forms = [hodlr(ip, offsets, sv, eps, None if rel else g)
                     for ip, sv, g in zip(inv_p, svds, norms)]
            ms = [f[0][np.ix_(back, back)] for f in forms]
            it = np.mean([cg_iterations(a, b, x0, ms[r]) for r, a, b, x0 in cases])
            stored, top = np.mean([f[1] for f in forms]), forms[0][2]
            print(f"| {eps:g} {label} | {stored / n / n:.2f} | {stored * 4 / 1e6:.2f} | "
                  f"{top[0]}, {top[1]} ({half}) | {it:.2f} |")

    if args.time is not None:
        ranks = hodlr(inv_p[0], offsets, svds[0], args.time, None)[3]
        # three chains' matrices: the chunk starts, or the first one's parameters scaled
        extra = [np.linalg.inv(blocks(refs[0][0] * f)[0])
                 for f in (1.05, 1.1)[:max(0, 3 - len(ref_inv))]]
        invs = (ref_inv + extra)[:3]
        invs_p = (inv_p + [e[np.ix_(perm, perm)] for e in extra])[:3]
        svds_t = svds + [block_svds(ip, offsets) for ip in invs_p[len(svds):]]
        forms = [_padded_factors(ip, offsets, sv, ranks) for ip, sv in zip(invs_p, svds_t)]
        rows = time_products(invs, forms, perm)
        print(f"\nproducts, HODLR at {args.time:g} of each block (ranks per level {ranks}), "
              "us per product:")
        print("| form | 1 thread | 3 threads at once |\n|---|---|---|")
        for name, one, three in rows:
            print(f"| {name} | {one:.0f} | {three:.0f} |")


if __name__ == "__main__":
    main()

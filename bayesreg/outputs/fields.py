"""Posterior displacement fields: nodal moments and draws, and their spread on image grids.

The stored draws hold ``u_b`` (sampled) and ``u_i`` (solved) per draw, and with a model
discrepancy ``d`` (sampled, :class:`bayesreg.model.posterior.Discrepancy`) the interior is
``u_i + d``; the functions here
put them in mesh node order and reduce them chunk by chunk, never holding all ``(S, N, 3)``
nodal draws at once.  Units: mm (displacements), mm^2 (covariances).
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

import numpy as np

from bayesreg.model.posterior import discrepancy_of
from bayesreg.model.posterior import node_slots as posterior_node_slots
from bayesreg.sampling.chains import available_cores

__all__ = ["node_slots", "nodal_draws", "nodal_mean", "nodal_spread", "voxel_norm_spread",
           "discrepancy_summary", "mesh_best_fit", "BEST_FIT_RIDGE", "CHUNK_DRAWS", "VOXEL_DRAWS",
           "SPREAD_MAX_BYTES"]


CHUNK_DRAWS = 2048  # draws per chunk of the nodal statistics (memory CHUNK x N x 3 doubles)


SPREAD_MAX_BYTES = 1 << 30  # the nodal covariances' accumulators, all threads together


def node_slots(problem):
    """Mesh node indices of the sampled boundary nodes and of the solved interior nodes, in
    the order of ``u_b`` and ``u_i`` (:func:`bayesreg.model.posterior.node_slots`)."""
    return posterior_node_slots(problem.posterior)


def nodal_draws(problem, result, rows):
    """Nodal displacement draws ``(S, N, 3)`` mm in mesh node order for ``rows`` (a slice or
    indices) of the pooled ``(C*D)`` draws: sampled boundary and solved interior nodes
    written straight to their places (no copy of all draws)."""
    b, i = node_slots(problem)
    n_chains, n_draws = result.positions.shape[:2]
    chain, draw = np.divmod(np.arange(n_chains * n_draws)[rows], n_draws)
    pos, ui = result.positions[chain, draw], result.interior[chain, draw]
    out = np.empty((len(pos), len(b) + len(i), 3))
    out[:, b] = pos[:, : 3 * len(b)].reshape(len(pos), len(b), 3)
    out[:, i] = ui
    d = discrepancy_of(problem.posterior, pos)
    if d is not None:
        out[:, i] += d
    return out


#: The ridge of :func:`mesh_best_fit`, relative to the mean diagonal of ``W^T W``.
BEST_FIT_RIDGE = 1e-3


def mesh_best_fit(w, target, u_ref, *, ridge: float = BEST_FIT_RIDGE) -> np.ndarray:
    """The nodal field whose FE interpolation is nearest a dense displacement: the mesh's
    resolution limit for a truth the model did not make.

    ``v = argmin ||W v - t||^2 + eps ||v - u_ref||^2`` per axis, ``eps = ridge * mean
    diag(W^T W)``: the least-squares projection of ``t`` onto the mesh's piecewise-linear
    fields over the voxels of ``W``, held near ``u_ref`` only where few voxels see a node
    (a boundary node outside the brain's voxels).  Where the truth varies within an
    element the projection differs from the truth at the nodes; the posterior, a
    distribution over nodal values, can at best centre on it.

    Parameters
    ----------
    w : (V, N) sparse matrix
        FE shape-function values at the voxels (rows of :func:`bayesreg.mesh.warp.interpolation_matrix`).
    target : (V, 3) ndarray
        The dense displacement at those voxels, mm.
    u_ref : (N, 3) ndarray
        Nodal values the ridge pulls toward (the truth at the nodes), mm.
    ridge : float
        > 0.

    Returns
    -------
    (N, 3) ndarray
        mm.

    Raises
    ------
    ValueError
        Shapes that do not match, or ``ridge <= 0``.
    """
    import scipy.sparse as sp
    import scipy.sparse.linalg as spla

    w = sp.csr_matrix(w)
    target, u_ref = np.asarray(target, np.float64), np.asarray(u_ref, np.float64)
    if target.shape != (w.shape[0], 3) or u_ref.shape != (w.shape[1], 3):
        raise ValueError(f"w {w.shape}, target {target.shape} and u_ref {u_ref.shape} do not "
                         "match ((V, N), (V, 3), (N, 3))")
    if not ridge > 0:
        raise ValueError(f"ridge must be > 0, got {ridge}")
    wtw = (w.T @ w).tocsc()
    eps = ridge * float(wtw.diagonal().mean())
    lu = spla.splu((wtw + eps * sp.identity(w.shape[1], format="csc")).tocsc())
    return lu.solve(np.asarray(w.T @ target) + eps * u_ref)


def _draw_chunks(result):
    n, chunk = result.positions.shape[0] * result.positions.shape[1], CHUNK_DRAWS
    return [slice(a, min(a + chunk, n)) for a in range(0, n, chunk)]


def nodal_mean(problem, result) -> np.ndarray:
    """Posterior mean nodal displacement ``(N, 3)`` mm: the means of the stored ``u_b`` and
    ``u_i`` draws put in mesh node order (no nodal draws assembled)."""
    b, i = node_slots(problem)
    mean = np.empty((len(b) + len(i), 3))
    mean[b] = result.positions[..., : 3 * len(b)].mean(axis=(0, 1)).reshape(len(b), 3)
    mean[i] = result.interior.mean(axis=(0, 1))
    d = discrepancy_of(problem.posterior, result.positions)
    if d is not None:
        mean[i] += d.mean(axis=(0, 1))
    return mean


def nodal_spread(problem, result, mean, *, block=128):
    """Per-node spread of the draws about ``mean``, over chunks of draws.

    Returns ``cov (3, N, N)`` (covariance per axis, mm^2), ``sd (N, 3)``, and the sd and
    inter-quartile range of ``|u|`` per node ``(N,)`` (mm).  Memory: the ``(C*D, N)``
    norms and one chunk, not the ``(C*D, N, 3)`` draws.
    """
    n_nodes = mean.shape[0]
    norm = np.empty((result.positions.shape[0] * result.positions.shape[1], n_nodes))

    def accumulate(rows):
        cov = np.zeros((3, n_nodes, n_nodes))
        for r in rows:
            x = nodal_draws(problem, result, r)
            norm[r] = np.linalg.norm(x, axis=2)
            x -= mean
            for c in range(3):
                xc = np.ascontiguousarray(x[:, :, c])
                cov[c] += xc.T @ xc
        return cov

    # the chunks shared among threads (BLAS and NumPy release the GIL), one (3, N, N)
    # accumulator each, as many as fit in SPREAD_MAX_BYTES (the 10k-node mesh: one)
    chunks = _draw_chunks(result)
    workers = max(1, min(available_cores(), len(chunks), SPREAD_MAX_BYTES // (24 * n_nodes * n_nodes)))
    with ThreadPoolExecutor(workers) as pool:
        covs = list(pool.map(accumulate, [chunks[k::workers] for k in range(workers)]))
    cov = covs.pop(0)
    for other in covs:  # in place: no third (3, N, N) array
        cov += other
    cov /= len(norm)
    sd = np.sqrt(np.maximum(np.stack([np.diag(cov[c]) for c in range(3)], axis=1), 0.0))
    norm_sd, norm_iqr = np.empty(n_nodes), np.empty(n_nodes)
    for a in range(0, n_nodes, block):
        cols = norm[:, a:a + block]
        norm_sd[a:a + block] = cols.std(axis=0)
        q75, q25 = np.quantile(cols, [0.75, 0.25], axis=0)
        norm_iqr[a:a + block] = q75 - q25
    return cov, sd, norm_sd, norm_iqr


VOXEL_DRAWS = 400  # evenly spaced draws behind the voxel-wise spread of |u|


def voxel_norm_spread(w, draws, max_draws=VOXEL_DRAWS, block=8192):
    """Per-voxel sd and inter-quartile range of ``|u|`` from FE-interpolated draws.

    ``w`` is the ``(P, N)`` interpolation matrix, ``draws`` ``(S, N, 3)``; at most
    ``max_draws`` evenly spaced draws are used, voxels in blocks (memory ``block x S x 3``).
    Returns two ``(P,)`` arrays, mm.
    """
    step = max(1, len(draws) // max_draws)
    d = np.asarray(draws[::step], np.float64)
    flat = d.transpose(1, 0, 2).reshape(d.shape[1], -1)  # (N, S*3)
    sd = np.zeros(w.shape[0])
    iqr = np.zeros(w.shape[0])
    rows = np.flatnonzero(np.diff(w.indptr) > 0)
    for a in range(0, len(rows), block):
        r = rows[a:a + block]
        vals = (w[r] @ flat).reshape(len(r), len(d), 3)
        norm = np.linalg.norm(vals, axis=2)
        sd[r] = norm.std(axis=1)
        q75, q25 = np.quantile(norm, [0.75, 0.25], axis=1)
        iqr[r] = q75 - q25
    return sd, iqr


def discrepancy_summary(problem, rms, d_mean, floor_mm: float) -> dict:
    """``run.json["discrepancy"]``: the posterior of the discrepancy's rms per interior node
    (``rms`` ``(C, D)`` mm: median, 5%, 95%), the largest ``|E[d]|`` over the nodes (``d_mean``
    ``(N, 3)`` mm, zero on the boundary) and where (world mm), and the prior's floor (mm)."""
    norm = np.linalg.norm(d_mean, axis=1)
    k = int(np.argmax(norm))
    return {"rms_mm": {"median": float(np.median(rms)), "q05": float(np.quantile(rms, 0.05)),
                       "q95": float(np.quantile(rms, 0.95))},
            "mean_norm_max_mm": float(norm[k]), "mean_norm_max_node": k,
            "mean_norm_max_world_mm": [float(v) for v in problem.mesh.nodes[k]],
            "floor_mm": float(floor_mm)}

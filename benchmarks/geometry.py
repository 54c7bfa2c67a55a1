"""The posterior's shape in the gradient kernels' coordinates: why a run's chains mix slowly.

NUTS runs on ``x = [u_b, d]`` (``d`` a model discrepancy, if any; ``c`` its coordinates low
rank) whitened at the mode, ``x = x_c + F w`` with ``F = R^-T`` and ``R R^T`` the
Gauss-Newton precision (``checkpoint/init.npz``: ``center``, ``sigma_0``), and on the free
parameters' logits.  Where the Laplace approximation holds, the draws' ``w`` have a
covariance near the identity.  For each run directory this prints the spectrum of that
covariance, the directions whose variance stands above white noise (the Marchenko-Pastur
edge ``(1 + sqrt(n_x / n))^2`` for ``n`` draws, doubled), how much of each lies in the
discrepancy, and how much of each free parameter's log the widest ten of them explain
(adjusted ``R^2``):
near 1, the displacement follows the parameters along a ridge that the whitening, made at
fixed parameters, does not see, and NUTS trajectories must be long to travel it.

The draws are read from ``posterior.nc`` for a finished run, else from the checkpoint's
chunks (an interrupted run); the problem, the centre and ``F`` from the run's checkpoint
(``output.checkpoint: true``, the default).

Usage (from the repository root)::

    python benchmarks/geometry.py runs/mismatch_discrepancy [more run directories]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

import bayesreg
from bayesreg.apply import load_posterior
from bayesreg.checkpoint import Checkpoint
from bayesreg.model.problem import assemble

#: The widest directions regressed on (at most).
TOP = 10


def positions(path: Path, problem) -> np.ndarray:
    """The draws ``(S, dim)``, chains pooled, in the position's layout ``[u_b, d (or c),
    phi]``: a finished run's (:func:`bayesreg.apply.load_posterior`), else the checkpoint's
    stored chunks (:meth:`bayesreg.checkpoint.Checkpoint.load_state`)."""
    if not (path / "posterior.nc").is_file():
        state = Checkpoint(path).load_state()
        if state is None or state[1] is None:
            raise SystemExit(f"{path}: neither posterior.nc nor checkpoint draws")
        pos = state[1][0]  # (C, D, dim)
        return pos.reshape(-1, pos.shape[-1])
    rp = load_posterior(path)
    parts = [rp.u_b.reshape(len(rp.u_b), -1)]
    disc = problem.posterior.discrepancy
    if disc is not None:
        d = rp.d.reshape(len(rp.d), -1)
        parts.append(d if disc.basis is None else d @ np.asarray(disc.basis))
    parts += [(rp.lam if p == "lam" else rp.mu)[:, [g]] for p, g in problem.layout.free]
    return np.concatenate(parts, axis=1)


def report(path: Path) -> None:
    ckpt = Checkpoint(path)
    init = ckpt.load_init()
    if init is None:
        raise SystemExit(f"{path}: no checkpoint/init.npz (the run needs output.checkpoint: true)")
    problem = assemble(ckpt.load_config(), ckpt.load_problem())
    post = problem.posterior
    if ckpt.load_config().model.discrepancy_prior.orthogonal:
        raise SystemExit(f"{path}: an orthogonal discrepancy's posterior.nc holds the displacing "
                         "part P d, not the sampled d of the chains' coordinates")
    factor, center = init.sigma[0], init.center
    if np.ndim(factor) != 2:
        raise SystemExit(f"{path}: no Laplace whitening (sampler.proposal is not laplace)")
    pos = positions(path, problem)
    n_x = post.n_displacement
    w = np.linalg.solve(factor, (pos[:, :n_x] - center[:n_x]).T).T
    nb3 = 3 * post.n_boundary
    g = whitened_geometry(w, np.log(pos[:, n_x:]), factor, nb3)
    print(f"{path}: {len(pos)} draws (chains pooled), {n_x} whitened coordinates "
          f"({nb3} of u_b, {n_x - nb3} of the discrepancy)")
    var = g["variance"]
    print(f"  per-coordinate variance: median {np.median(var):.2f}, 90% {np.quantile(var, 0.9):.2f}, "
          f"max {var.max():.2f}")
    vals = g["eigenvalues"]
    print(f"  covariance eigenvalues: largest {np.round(vals[::-1][:6], 1).tolist()}, smallest "
          f"{np.round(vals[:3], 3).tolist()}; white noise reaches {g['edge']:.2f}")
    print(f"  directions above twice that: {g['n_wide']}")
    if not g["n_wide"]:
        return
    k = len(g["share"])
    if n_x > nb3:
        print(f"  share in the discrepancy of the {k} widest: {np.round(g['share'], 2).tolist()}")
    r2 = ", ".join(f"{name} {v:.2f}" for name, v in zip(problem.layout.free_names, g["r2"]))
    print(f"  adjusted R^2 of each free log-parameter on the {k} widest: {r2}")


def whitened_geometry(w, log_phi, factor, n_b3: int, top: int = TOP) -> dict:
    """The shape of draws in whitened coordinates.

    Parameters
    ----------
    w : (n, n_x) array
        The draws' whitened displacement coordinates.
    log_phi : (n, n_free) array
        The same draws' free parameters, logged.
    factor : (n_x, n_x) array
        ``F`` (``x = x_c + F w``): maps a direction of ``w`` to one of ``x``.
    n_b3 : int
        ``3 n_b``: ``x``'s entries of ``u_b`` (the rest are the discrepancy's).
    top : int
        At most this many of the widest directions are examined.

    Returns
    -------
    dict
        ``variance`` ``(n_x,)`` per coordinate; ``eigenvalues`` ``(n_x,)`` ascending of the
        covariance; ``edge``, the Marchenko-Pastur edge ``(1 + sqrt(n_x / n))^2``;
        ``n_wide``, the eigenvalues above twice it; ``share`` ``(k,)``, the squared norm in
        the discrepancy's entries of ``x`` of each of the ``k = min(n_wide, top)`` widest
        directions, widest first; ``r2`` ``(n_free,)``, each log-parameter's adjusted
        ``R^2`` on the draws' projections onto them (NaN without wide directions).
    """
    n, n_x = w.shape
    wc = w - w.mean(axis=0)
    vals, vecs = np.linalg.eigh(wc.T @ wc / n)
    edge = (1 + np.sqrt(n_x / n)) ** 2
    n_wide = int(np.sum(vals > 2 * edge))
    order = np.argsort(vals)[::-1][:min(n_wide, top)]
    dirs = vecs[:, order]
    mapped = np.asarray(factor) @ dirs
    share = np.sum(mapped[n_b3:] ** 2, axis=0) / np.sum(mapped ** 2, axis=0)
    r2 = np.full(log_phi.shape[1], np.nan)
    if len(order):
        proj = np.c_[wc @ dirs, np.ones(n)]
        for k, y in enumerate(np.asarray(log_phi).T):
            resid = y - proj @ np.linalg.lstsq(proj, y, rcond=None)[0]
            r2[k] = 1 - (resid.var() / y.var()) * (n - 1) / (n - len(order) - 1)
    return {"variance": wc.var(axis=0), "eigenvalues": vals, "edge": edge, "n_wide": n_wide,
            "share": share, "r2": r2}


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("runs", nargs="+", type=Path, help="run directories")
    args = parser.parse_args(argv)
    bayesreg.configure_jax()
    for path in args.runs:
        report(path)


if __name__ == "__main__":
    main()

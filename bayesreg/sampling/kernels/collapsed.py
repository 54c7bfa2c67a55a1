"""The collapsed moves' proposals (:mod:`bayesreg.sampling.kernels.gibbs`, part 3): a move
of the elastic parameters ``eta -> eta'`` that carries the displacement block along by a
deterministic map, accepted with the log-density's ratio plus the map's log-Jacobian.

* :func:`collapsed_proposal` (``carry="conditional"``): by the target's Gaussian of the
  displacement given the parameters, ``x' = m' + C'^-T C^T (x - m)``.
* :func:`displacement_proposal` (``carry="displacement"``, with a model discrepancy): ``u_b``
  stays and the discrepancy takes up the FE interior's change, so that every node's
  displacement stays.

Both maps are undone by the move from ``eta'`` back, so each move is reversible.
"""

from __future__ import annotations

import jax.numpy as jnp
from jax.scipy.linalg import solve_triangular

from bayesreg.sampling.kernels.target import Target

__all__ = ["CARRIES", "collapsed_proposal", "displacement_proposal"]

#: How the collapsed moves carry the displacement (``sampler.carry``).
CARRIES = ("conditional", "displacement")


def displacement_proposal(target: Target, w, eta, eta_p, interior, interior_p):
    """A collapsed move's proposal that keeps every node's displacement: ``u_b`` stays and the
    discrepancy takes up the FE interior's change, ``d' = d + interior - interior_p``
    (:attr:`~bayesreg.sampling.kernels.target.Target.shift`; low rank, its projection on the
    modes).

    Parameters
    ----------
    target : Target
        With ``shift`` (a model discrepancy) and free parameters.
    w : (n,) array
        Coordinates of the displacement block now.
    eta, eta_p : (n_free,) arrays
        The parameters' logits now and proposed.
    interior, interior_p : (n_i, 3) arrays
        The FE interior solve ``H(phi) u_b`` at ``eta`` and at ``eta_p`` (mm).

    Returns
    -------
    (n,) array
        Coordinates of the proposal at ``eta_p``.  The map is a shear by a function of
        ``u_b`` alone (Jacobian 1), and the move from ``eta_p`` back undoes it.
    """
    n_f = target.n_free
    x_p = target.shift(target.position(w, eta)[:-n_f], interior - interior_p)
    return target.coordinates(jnp.concatenate([x_p, target.position(w, eta_p)[-n_f:]]))[0]


def collapsed_proposal(target: Target, w, eta, eta_p, tau, mean, chol):
    """A collapsed move's proposal: the displacement carried from the parameters ``eta`` to
    ``eta_p`` by the target's Gaussian of it given them
    (:attr:`~bayesreg.sampling.kernels.target.Target.conditional`), ``x' = m' + C'^-T C^T (x -
    m)`` (the same standardised residual; ``x`` the displacement block of ``(w, eta)``).

    Parameters
    ----------
    target : Target
        With ``conditional`` and free parameters.
    w : (n,) array
        Coordinates of the displacement now.
    eta, eta_p : (n_free,) arrays
        The parameters' logits now and proposed.
    tau : () array
        The discrepancy's precision of the moves (ignored without a
        :attr:`~bayesreg.sampling.kernels.target.Target.mixture`).
    mean, chol : (n,), (n, n) arrays
        ``target.conditional(eta, tau)``.

    Returns
    -------
    w_p : (n,) array
        Coordinates of ``x'``.
    mean_p, chol_p : (n,), (n, n) arrays
        ``target.conditional(eta_p, tau)``.
    log_correction : () array
        The acceptance's log-ratio less that of the target's log-density (the kernel's
        ``evaluate``): the Jacobian ``log det C - log det C'`` plus, with a mixture, its
        ``log_ratio`` at ``x'`` less at ``x`` (the log-density at ``tau`` instead of the
        marginal's).
    """
    n_f = target.n_free
    x = target.position(w, eta)[:-n_f]
    mean_p, chol_p = target.conditional(eta_p, tau)
    x_p = mean_p + solve_triangular(chol_p, chol.T @ (x - mean), lower=True, trans="T")
    w_p, _ = target.coordinates(jnp.concatenate([x_p, target.position(w, eta_p)[-n_f:]]))
    log_corr = jnp.sum(jnp.log(jnp.diag(chol))) - jnp.sum(jnp.log(jnp.diag(chol_p)))
    if target.mixture is not None:
        log_corr = log_corr + target.mixture.log_ratio(x_p, tau) - target.mixture.log_ratio(x, tau)
    return w_p, mean_p, chol_p, log_corr

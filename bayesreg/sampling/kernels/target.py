"""The posterior as the gradient kernels see it: pure functions of ``(w, eta)``.

``u_b = c + F w`` (``c`` the start's centre, ``F`` a fixed factor, by default ``R^-T`` of the
Gauss-Newton precision ``R R^T`` at the start: a constant affine map, so the target is
unchanged) and ``eta`` the logit of the free elastic parameters on their prior support
(:func:`bayesreg.model.parameters.from_unconstrained`, with the log-Jacobian).  With ``condensed``
the interior comes from a cached dense map ``u_i = H(lam, mu) u_b`` (no CG solve in the
gradient), else from the CG solve with implicit differentiation.
"""

from __future__ import annotations

from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
from jax.scipy.linalg import cho_solve

from bayesreg.fem.normaliser import add_normaliser
from bayesreg.model.parameters import from_unconstrained, to_unconstrained
from bayesreg.model.posterior import (
    Posterior, condensation, log_density, log_density_condensed, log_normaliser, preconditioner,
    prior_precision)

__all__ = ["Cache", "Target", "make_target", "joint_target", "laplace_likelihood"]


class Cache(NamedTuple):
    """What depends on the elastic parameters only, rebuilt when they move.

    Attributes
    ----------
    h : (3 n_i, 3 n_b) or (0,)
        Dense interior map (condensed targets), else an empty placeholder.
    log_norm : ()
        ``(1/2) log pdet S`` (exact normaliser) or 0 (the paper's prior).
    precond : DensePreconditioner or None
        The CG preconditioner of the solves (targets made with ``precondition=True``):
        built at the chain's parameters when a chunk starts (:meth:`Target.build_precond`)
        and kept when the rest of the cache is rebuilt (it only has to stay near
        ``K_ii^-1``; the solves meet the same tolerance).
    """

    h: jax.Array
    log_norm: jax.Array
    precond: object = None


class Target(NamedTuple):
    """The posterior seen by the Gibbs kernel (pure functions; see :func:`make_target`).

    Attributes
    ----------
    u_logdensity : callable
        ``(w, eta, cache, interior) -> logp``: log-density of ``w`` given ``eta``, up to
        terms that do not depend on ``w``; differentiable in ``w``.
    u_evaluate : callable
        ``(w, eta, cache, interior) -> (logp, interior, cg_iterations, solve_ok)``, the same
        value with the interior solution at ``w``.
    evaluate : callable
        ``(w, eta, interior, log_norm, precond=None) -> (logp_eta, logp_natural, interior,
        cg_iterations, solve_ok)``: the joint log-density over ``(w, eta)`` (with the
        log-Jacobian and the normaliser ``log_norm``) and over the natural parameters
        ``(u_b, lam, mu)`` (with the normaliser, without the Jacobian), from a solve that
        does not use the map ``H`` (preconditioned by ``precond`` if given).  The kernel passes
        ``precond`` only to targets with a ``build_precond``: a target without one may take
        the first four arguments alone.
    log_norm : callable
        ``eta -> ()`` the normaliser term (0 for the paper's prior).
    build_cache : callable
        ``(eta, log_norm) -> Cache`` (without a preconditioner).
    build_precond : callable or None
        ``eta -> DensePreconditioner`` at those parameters, or ``None`` (block Jacobi).
    position : callable
        ``(w, eta) -> theta``, the stored position ``[u_b.ravel(), phi]``.
    coordinates : callable
        ``theta -> (w, eta)``, the inverse of ``position``.
    n_free : int
    condensed : bool
        The gradient moves take the interior from the cached map ``H`` (no CG solve).
    preconditioner : str
        The CG preconditioner of the target's solves: ``"dense"`` (``build_precond``),
        ``"spectral"`` or ``"block-jacobi"`` (the posterior's own).
    conditional : callable or None
        ``eta -> (mean (3 n_b,), chol (3 n_b, 3 n_b))``: a Gaussian approximation
        ``N(mean, (chol chol^T)^-1)`` of ``u_b`` given the parameters (targets made with
        ``likelihood``), what the kernel's collapsed moves transport ``u_b`` with.
    log_jacobian : callable or None
        A joint target's (:func:`joint_target`: ``w`` holds the elastic coordinates too, and
        ``n_free`` is 0): ``w -> ()``, the log-Jacobian inside ``u_logdensity`` that the
        natural log-density lacks.  ``None`` for a target of ``u_b`` alone.
    correction : callable or None
        A joint target whose trajectories see a surrogate of the exact normaliser
        (:func:`joint_target` ``surrogate``): ``w -> ()``, the exact normaliser less the
        surrogate at ``w``'s parameters (NaN where the exact one fails), what the kernel's
        Metropolis correction after each trajectory uses (:mod:`bayesreg.sampling.kernels.gibbs`).
    """

    u_logdensity: Callable
    u_evaluate: Callable
    evaluate: Callable
    log_norm: Callable
    build_cache: Callable
    position: Callable
    coordinates: Callable
    n_free: int
    build_precond: Callable | None = None
    condensed: bool = False
    preconditioner: str = "block-jacobi"
    conditional: Callable | None = None
    log_jacobian: Callable | None = None
    correction: Callable | None = None


def make_target(post: Posterior, *, center_u, factor, exact: bool, condensed: bool, rtol=1e-8,
                maxiter=1000, precondition: bool = False, likelihood=None,
                factor_inv=None) -> Target:
    """:class:`Target` of a :class:`bayesreg.model.posterior.Posterior`.

    Parameters
    ----------
    post : Posterior
    center_u : (3 n_b,) array
        ``c`` of ``u_b = c + F w`` (mm).
    factor : (3 n_b,) or (3 n_b, 3 n_b) array
        ``F`` (mm per unit of ``w``): a vector of scales or a dense matrix.
    exact : bool
        Include the exact normaliser of the elastic prior (``prior_normaliser: exact``).
    condensed : bool
        Gradient moves take the interior from the cached dense map ``H`` instead of a CG solve.
    rtol, maxiter
        CG tolerance and cap (see :func:`bayesreg.model.posterior.log_density`).
    precondition : bool
        Precondition the CG solves (the elastic moves', and the gradient moves' without
        ``condensed``) by the dense ``K_ii^-1`` at the chain's parameters when the chunk
        started (:func:`bayesreg.model.posterior.preconditioner`): a few iterations instead of
        a hundred, the same tolerance.
    likelihood : (A, b), optional
        A Gaussian approximation ``exp(b^T u_b - u_b^T A u_b / 2)`` of the likelihood in
        ``u_b`` (``A`` ``(3 n_b, 3 n_b)`` symmetric positive semi-definite, ``b`` ``(3 n_b,)``;
        :func:`laplace_likelihood`): then the target has a :attr:`Target.conditional`, the
        Gaussian ``u_b | phi`` it makes with the elastic prior, precision ``A + Q(phi)``
        (:func:`bayesreg.model.posterior.prior_precision`), mean ``(A + Q(phi))^-1 b``.
    factor_inv : (3 n_b, 3 n_b) array, optional
        ``F^-1`` of a dense ``factor`` where the caller has it (a target built inside a
        transition, as :func:`bayesreg.sampling.kernels.gibbs.build_kernel` does for
        per-chain data, would otherwise invert ``F`` at every step); computed otherwise.

    Returns
    -------
    Target

    """

    c = jnp.asarray(center_u)
    f = jnp.asarray(factor)
    nb3 = c.shape[0]
    dense = f.ndim == 2
    if factor_inv is not None:
        f_inv = jnp.asarray(factor_inv)
    else:
        f_inv = jnp.linalg.inv(f) if dense else 1.0 / f

    def u_of(w):
        return c + (f @ w if dense else f * w)

    def theta_of(w, eta):
        phi, _ = from_unconstrained(post.prior, eta)
        return jnp.concatenate([u_of(w), phi])

    def u_evaluate(w, eta, cache, interior):
        theta = theta_of(w, eta)
        if condensed:
            lp, aux = log_density_condensed(post, theta, cache.h)
        else:
            lp, aux = log_density(post, theta, interior, rtol=rtol, maxiter=maxiter, precond=cache.precond)
        return lp, aux.interior, aux.solve.iterations, aux.solve.converged

    def u_logdensity(w, eta, cache, interior):
        return u_evaluate(w, eta, cache, interior)[0]

    def log_norm(eta):
        if not exact:
            return jnp.zeros(())
        return log_normaliser(post, from_unconstrained(post.prior, eta)[0])

    def evaluate(w, eta, interior, log_norm_value, precond=None):
        _, log_jac = from_unconstrained(post.prior, eta)
        lp, aux = log_density(post, theta_of(w, eta), interior, rtol=rtol, maxiter=maxiter, precond=precond)
        lp_nat = add_normaliser(lp, log_norm_value)
        return lp_nat + log_jac, lp_nat, aux.interior, aux.solve.iterations, aux.solve.converged

    def build_cache(eta, log_norm_value):
        h = condensation(post, theta_of(jnp.zeros(nb3), eta)) if condensed else jnp.zeros((0,))
        return Cache(h, jnp.asarray(log_norm_value, jnp.float64))

    def coordinates(theta):
        d = theta[:nb3] - c
        w = f_inv @ d if dense else f_inv * d
        return w, to_unconstrained(post.prior, theta[nb3:])

    def build_precond(eta):
        return preconditioner(post, theta_of(jnp.zeros(nb3), eta))

    conditional = None
    if likelihood is not None:
        a_lik, b_lik = (jnp.asarray(v) for v in likelihood)

        def conditional(eta):
            phi, _ = from_unconstrained(post.prior, eta)
            prec = a_lik + prior_precision(post, phi)
            chol = jnp.linalg.cholesky(0.5 * (prec + prec.T))
            return cho_solve((chol, True), b_lik), chol

    if precondition:
        name = "dense"
    else:
        name = "spectral" if post.spectral is not None else "block-jacobi"
    return Target(u_logdensity, u_evaluate, evaluate, log_norm, build_cache, theta_of, coordinates,
                  int(post.n_free), build_precond if precondition else None, bool(condensed), name,
                  conditional)


def joint_target(base: Target, *, center_eta, eta_scale, log_jacobian, surrogate=None) -> Target:
    """The target of one gradient kernel over ``u_b`` and the elastic parameters together.

    The coordinates are ``z = [w, v]``: ``w`` those of ``base`` (``u_b = c + F w``) and
    ``v`` the free parameters' logits, ``eta = center_eta + eta_scale * v``.  The log-density
    is ``base.evaluate``'s over ``(w, eta)`` (with the log-Jacobian of ``eta``, and the
    exact normaliser where ``base`` has one), from the CG solve of the interior with
    implicit differentiation (:mod:`bayesreg.fem.solver`), so ``jax.grad`` moves ``u_b`` and
    the parameters along one trajectory: no Gibbs alternation between the parameters and
    the ``u_b`` that pins them down.  The returned target has ``n_free = 0`` (the Gibbs
    kernel then makes no elastic moves) and a :attr:`Target.log_jacobian`.  Its CG
    preconditioner (``base``'s dense one, if any) is built at ``center_eta`` whatever the
    chain's parameters: it only has to stay near ``K_ii^-1``, and the tolerance is the same.

    With a ``surrogate`` of ``base``'s normaliser, the log-density (and so every leapfrog
    step) holds the surrogate instead, and the target's :attr:`Target.correction` gives the
    exact normaliser less the surrogate: the kernel accepts each trajectory's end with the
    Metropolis probability ``min(1, exp(correction(z') - correction(z)))``, which makes the
    chain's stationary distribution the exact posterior whatever the surrogate (the
    trajectory is a reversible kernel of the surrogate posterior; Liu 2001, Sec. 9.4;
    Christen and Fox 2005), at one exact normaliser per transition instead of one exact
    gradient per leapfrog step.

    Parameters
    ----------
    base : Target
        :func:`make_target`'s target, with ``n_free > 0``.
    center_eta : (n_free,) array
        Unconstrained parameters at ``v = 0`` (the starts' centre).
    eta_scale : float or (n_free,) array
        Scale of ``v`` (logit units per unit of ``v``): the mass matrix's adaptation in
        the warm-up sees ``v`` at about the scale of ``w``.
    log_jacobian : callable
        ``eta -> ()``: the log-Jacobian that ``base.evaluate``'s first value adds to its
        natural log-density (:func:`bayesreg.model.parameters.from_unconstrained`'s for a
        posterior's target).
    surrogate : callable, optional
        ``eta -> ()``: a smooth, cheap approximation of ``base.log_norm``
        (:func:`bayesreg.model.posterior.surrogate_normaliser`).

    Returns
    -------
    Target

    Raises
    ------
    ValueError
        ``base`` without free parameters, or ``center_eta`` of another length.
    """
    n = int(base.n_free)
    if n == 0:
        raise ValueError("a joint target needs free elastic parameters")
    eta_c = jnp.asarray(center_eta, jnp.float64)
    if eta_c.shape != (n,):
        raise ValueError(f"center_eta must have shape ({n},), got {eta_c.shape}")
    scale = jnp.broadcast_to(jnp.asarray(eta_scale, jnp.float64), (n,))
    empty = jnp.zeros((0,))

    def split(z):
        return z[:-n], eta_c + scale * z[-n:]

    log_norm = base.log_norm if surrogate is None else surrogate

    def evaluate(z, _eta, interior, _log_norm=None, precond=None):
        w, eta = split(z)
        if base.build_precond is None:
            return base.evaluate(w, eta, interior, log_norm(eta))
        return base.evaluate(w, eta, interior, log_norm(eta), precond)

    correction = None
    if surrogate is not None:
        def correction(z):
            eta = split(z)[1]
            return base.log_norm(eta) - surrogate(eta)

    def u_evaluate(z, _eta, cache, interior):
        lz, _, interior, its, ok = evaluate(z, _eta, interior, None, cache.precond)
        return lz, interior, its, ok

    def coordinates(theta):
        w, eta = base.coordinates(theta)
        return jnp.concatenate([w, (eta - eta_c) / scale]), empty

    build_precond = None
    if base.build_precond is not None:
        def build_precond(_eta):
            return base.build_precond(eta_c)

    return Target(
        u_logdensity=lambda z, e, cache, interior: u_evaluate(z, e, cache, interior)[0],
        u_evaluate=u_evaluate, evaluate=evaluate, log_norm=lambda _eta: jnp.zeros(()),
        build_cache=lambda _eta, _ln: Cache(jnp.zeros((0,)), jnp.zeros(())),
        position=lambda z, _eta: base.position(*split(z)), coordinates=coordinates, n_free=0,
        build_precond=build_precond, condensed=False, preconditioner=base.preconditioner,
        log_jacobian=lambda z: log_jacobian(split(z)[1]), correction=correction)


def laplace_likelihood(post: Posterior, theta0, a_lik):
    """``(A, b)`` of :func:`make_target`'s ``likelihood``: the likelihood linearised at the
    position ``theta0`` ``(dim,)`` with curvature ``a_lik`` ``(3 n_b, 3 n_b)`` (its
    Gauss-Newton curvature there: ``2 J^T J / T_s``), ``b = A u_0 + g`` with ``g`` the
    gradient in ``u_b`` of ``log p`` plus the elastic prior's part at ``theta0`` (everything
    in ``log p`` but the elastic prior: the similarity, the skull barrier), by JAX.
    """
    if post.discrepancy is not None:
        raise ValueError("the collapsed moves' Gaussian likelihood is of u_b alone: not with a "
                         "model discrepancy")
    theta0 = jnp.asarray(theta0)
    nb3 = 3 * post.n_boundary
    h = condensation(post, theta0)
    phi0 = theta0[nb3:]

    def logp_u(u):
        return log_density_condensed(post, jnp.concatenate([u, phi0]), h)[0]

    u0 = theta0[:nb3]
    g = jax.grad(logp_u)(u0) + prior_precision(post, phi0) @ u0
    a_lik = jnp.asarray(a_lik)
    return a_lik, a_lik @ u0 + g

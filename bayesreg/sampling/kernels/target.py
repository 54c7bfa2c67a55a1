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
    Posterior, condensation, data_log_likelihood, discrepancy_map, discrepancy_mixture_log_ratio,
    discrepancy_of, discrepancy_precision_draw, discrepancy_stiffness, interior_map_and_precision, log_density,
    log_density_condensed, log_normaliser, preconditioner, prior_precision, shift_discrepancy)

__all__ = ["Cache", "Mixture", "Target", "make_target", "joint_target", "laplace_likelihood",
           "nodal_laplace_likelihood"]


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


class Mixture(NamedTuple):
    """A Student prior on part of the displacement block as a Gaussian scale mixture (the
    model discrepancy's, :class:`bayesreg.model.posterior.Discrepancy`): the collapsed moves
    draw its precision ``tau`` from its conditional, then move at that ``tau``, where the
    prior is Gaussian and so is their approximation of the displacement given the
    parameters.

    Attributes
    ----------
    draw : callable
        ``(key, x) -> tau``: ``tau`` ``()`` given the displacement block ``x``
        ``(n_displacement,)`` (:func:`bayesreg.model.posterior.discrepancy_precision_draw`).
    log_ratio : callable
        ``(x, tau) -> ()``: the log-density at ``tau`` less the marginal's, up to a constant
        (:func:`bayesreg.model.posterior.discrepancy_mixture_log_ratio`).
    """

    draw: Callable
    log_ratio: Callable


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
        ``(eta, tau) -> (mean (n,), chol (n, n))``: a Gaussian approximation ``N(mean,
        (chol chol^T)^-1)`` of the displacement block (``u_b``, ``n = 3 n_b``; with a model
        discrepancy ``[u_b, d]``, ``n = n_displacement``) given the parameters and, with a
        :attr:`mixture`, the discrepancy's precision ``tau`` (ignored without one): what the
        kernel's collapsed moves transport the displacement with (targets made with
        ``likelihood``).
    log_jacobian : callable or None
        A joint target's (:func:`joint_target`: ``w`` holds the elastic coordinates too, and
        ``n_free`` is 0): ``w -> ()``, the log-Jacobian inside ``u_logdensity`` that the
        natural log-density lacks.  ``None`` for a target of ``u_b`` alone.
    correction : callable or None
        A joint target whose trajectories see a surrogate of the exact normaliser
        (:func:`joint_target` ``surrogate``): ``w -> ()``, the exact normaliser less the
        surrogate at ``w``'s parameters (NaN where the exact one fails), what the kernel's
        Metropolis correction after each trajectory uses (:mod:`bayesreg.sampling.kernels.gibbs`).
    mixture : Mixture or None
        The model discrepancy's prior as a scale mixture (targets of a posterior with one),
        which the collapsed moves condition on.
    shift : callable or None
        ``(x, delta) -> x'``: the displacement block ``x`` ``(n_displacement,)`` with the
        discrepancy moved by ``delta`` ``(n_i, 3)`` mm
        (:func:`bayesreg.model.posterior.shift_discrepancy`; targets of a posterior with a
        model discrepancy): what the collapsed moves that keep the nodal displacement use.
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
    mixture: Mixture | None = None
    shift: Callable | None = None


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
        With a model discrepancy, of the nodal displacement ``u = [u_b, u_i]`` instead (``A``
        ``(3N, 3N)``, ``b`` ``(3N,)``, boundary DOFs first; :func:`nodal_laplace_likelihood`):
        the conditional of ``x = [u_b, d]`` given ``phi`` and the discrepancy's precision
        ``tau`` is then the Gaussian of ``u = L(phi) x`` (``u_i = H(phi) u_b + d``, ``d = V
        c`` low rank) under it and the prior ``N(0, Q(phi)^-1) x N(0, (tau K0_ii)^-1)``:
        precision ``L^T A L + diag(Q(phi), tau K0_ii)``, mean its inverse times ``L^T b``.
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
    if likelihood is not None and post.discrepancy is not None:
        conditional = _discrepancy_conditional(post, *likelihood)
    elif likelihood is not None:
        a_lik, b_lik = (jnp.asarray(v) for v in likelihood)

        def conditional(eta, _tau=None):
            phi, _ = from_unconstrained(post.prior, eta)
            prec = a_lik + prior_precision(post, phi)
            chol = jnp.linalg.cholesky(0.5 * (prec + prec.T))
            return cho_solve((chol, True), b_lik), chol

    mixture = shift = None
    if post.discrepancy is not None:
        mixture = Mixture(
            draw=lambda key, x: discrepancy_precision_draw(
                post, key, discrepancy_of(post, x, projected=False)),
            log_ratio=lambda x, tau: discrepancy_mixture_log_ratio(
                post, discrepancy_of(post, x, projected=False), tau))

        def shift(x, delta):
            return shift_discrepancy(post, x, delta)

    if precondition:
        name = "dense"
    else:
        name = "spectral" if post.spectral is not None else "block-jacobi"
    return Target(u_logdensity, u_evaluate, evaluate, log_norm, build_cache, theta_of, coordinates,
                  int(post.n_free), build_precond if precondition else None, bool(condensed), name,
                  conditional, mixture=mixture, shift=shift)


def _discrepancy_conditional(post: Posterior, a_nodal, b_nodal):
    """``(eta, tau) -> (mean, chol)`` of ``x = [u_b, d]`` (``[u_b, c]`` low rank) given the
    parameters and the discrepancy's precision, from the likelihood ``(A, b)`` of the nodal
    displacement (boundary DOFs first; see :func:`make_target`'s ``likelihood``)."""
    nb3 = 3 * post.n_boundary
    a, b = jnp.asarray(a_nodal), jnp.asarray(b_nodal)
    n = nb3 + 3 * post.op.n_interior
    if a.shape != (n, n) or b.shape != (n,):
        raise ValueError(f"a model discrepancy's likelihood is of the nodal displacement: A "
                         f"({n}, {n}) and b ({n},), got {a.shape} and {b.shape}")
    a_bb, a_bi, a_ii, b_b, b_i = a[:nb3, :nb3], a[:nb3, nb3:], a[nb3:, nb3:], b[:nb3], b[nb3:]
    basis = post.discrepancy.basis
    k0 = discrepancy_stiffness(post)
    if basis is None and post.discrepancy.sensitivities is None:
        a_dd, b_d = a_ii, b_i
    else:  # the interior moves by M x_d (d = V c; orthogonal: P d, P V c)
        basis = jnp.asarray(discrepancy_map(post))
        a_dd, b_d = basis.T @ a_ii @ basis, basis.T @ b_i

    def conditional(eta, tau):
        phi, _ = from_unconstrained(post.prior, eta)
        h, q = interior_map_and_precision(post, phi)
        cross = a_bi + h.T @ a_ii  # (3 n_b, 3 n_i): L's boundary rows against the interior
        # L^T A L's boundary block: a_bb + a_bi H + H^T a_ib + H^T a_ii H
        p_bb = a_bb + (a_bi @ h).T + cross @ h + q
        p_bd = cross if basis is None else cross @ basis
        prec = jnp.block([[p_bb, p_bd], [p_bd.T, a_dd + tau * k0]])
        chol = jnp.linalg.cholesky(0.5 * (prec + prec.T))
        rhs = jnp.concatenate([b_b + h.T @ b_i, b_d])
        return cho_solve((chol, True), rhs), chol

    return conditional


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


def nodal_laplace_likelihood(post: Posterior, u0, a_nodal):
    """``(A, b)`` of :func:`make_target`'s ``likelihood`` for a posterior with a model
    discrepancy: the data terms (:func:`bayesreg.model.posterior.data_log_likelihood`: the
    similarity and the skull barrier) linearised in the nodal displacement at ``u0``
    ``(N, 3)`` mm with curvature ``a_nodal`` ``(3N, 3N)`` (DOFs ``3 node + axis``; the
    Gauss-Newton curvature there, ``2 J^T J / T_s``), ``b = A u_0 + g`` with ``g`` the data
    terms' gradient, by JAX.  Both are returned in the order ``[u_b, u_i]``: the boundary
    nodes' DOFs (:attr:`~bayesreg.model.posterior.Posterior.boundary` order), then the
    interior nodes' (the solver's order).

    Raises
    ------
    ValueError
        ``u0`` not ``(N, 3)`` or ``a_nodal`` not ``(3N, 3N)``.
    """
    u0 = jnp.asarray(u0)
    n3 = 3 * post.nodes.shape[0]
    if u0.shape != tuple(post.nodes.shape) or jnp.shape(a_nodal) != (n3, n3):
        raise ValueError(f"nodal_laplace_likelihood needs u0 {tuple(post.nodes.shape)} and a_nodal "
                         f"({n3}, {n3}), got {u0.shape} and {jnp.shape(a_nodal)}")
    order = jnp.argsort(post.perm)  # node of each position in concat(boundary, interior)
    dofs = (3 * order[:, None] + jnp.arange(3)).reshape(-1)
    g = jax.grad(lambda u: data_log_likelihood(post, u))(u0).reshape(-1)[dofs]
    a = jnp.asarray(a_nodal)[dofs][:, dofs]
    return a, a @ u0.reshape(-1)[dofs] + g


def laplace_likelihood(post: Posterior, theta0, a_lik):
    """``(A, b)`` of :func:`make_target`'s ``likelihood``: the likelihood linearised at the
    position ``theta0`` ``(dim,)`` with curvature ``a_lik`` ``(3 n_b, 3 n_b)`` (its
    Gauss-Newton curvature there: ``2 J^T J / T_s``), ``b = A u_0 + g`` with ``g`` the
    gradient in ``u_b`` of ``log p`` plus the elastic prior's part at ``theta0`` (everything
    in ``log p`` but the elastic prior: the similarity, the skull barrier), by JAX.
    """
    if post.discrepancy is not None:
        raise ValueError("laplace_likelihood is of u_b alone: with a model discrepancy the "
                         "likelihood is of the nodal displacement (nodal_laplace_likelihood)")
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

"""The posterior mode: where the chains start (``init.method: mode``).

:func:`find_mode` maximises the log posterior by L-BFGS (optax, zoom line search) with JAX
gradients through the interior solve.  It takes a posterior and plain arguments, no config.
"""

from __future__ import annotations

from functools import partial
from types import SimpleNamespace
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import optax

from bayesreg.mesh.constraints import element_volumes, inversion_barrier
from bayesreg.fem.normaliser import add_normaliser
from bayesreg.model.posterior import (
    Posterior, log_normaliser, nodal_displacement, normaliser_surrogate, split_position,
    surrogate_normaliser, with_skull_barrier)
from bayesreg.inference.targets import logdensity_fn

__all__ = ["ModeSearch", "find_mode", "MODE_BARRIER_MM", "MODE_WIDE_BARRIER_MM", "MODE_VOLUME_RATIO",
           "MODE_STALL_NATS", "MODE_STALL_ITERATIONS", "SURROGATE_ROUNDS"]

MODE_BARRIER_MM = 1.0
"""Width (mm) of the skull barrier that :func:`find_mode` adds to a model without one."""

MODE_WIDE_BARRIER_MM = 3.0
"""Width (mm) of the skull barrier of :func:`find_mode`'s first stage (``u_b`` alone)."""

MODE_VOLUME_RATIO = 0.1
"""Volume ratio below which :func:`find_mode`'s objective bends down against an element's
inversion (:func:`bayesreg.mesh.constraints.inversion_barrier`)."""

MODE_STALL_NATS, MODE_STALL_ITERATIONS = 0.1, 100
"""An L-BFGS stage of :func:`find_mode` stops once its best ``log p`` gained less than
``MODE_STALL_NATS`` over the last ``MODE_STALL_ITERATIONS`` iterations: a crawl along a ridge,
whose gain is far below the chains' own spread of ``log p`` (about ``sqrt(dim / 2)`` nats)."""

SURROGATE_ROUNDS = 4
"""At most this many rounds of the parameters' search with the normaliser's surrogate
(:func:`find_mode`)."""


class ModeSearch(NamedTuple):
    """Result of :func:`find_mode`.

    Attributes
    ----------
    theta : (dim,) ndarray
        The mode found, ``[u_b.ravel() (mm), phi]``.
    logp_start, logp_mode : float
        The searched objective (the barriers included) at the start (with the first
        stage's wide barrier) and at the result.
    iterations : int
        L-BFGS iterations, all stages.
    message : str
        Why the search stopped (``"converged: ..."``, ``"stalled: ..."``
        (:data:`MODE_STALL_NATS`), ``"reached N iterations"``, or that the line search found
        no feasible step: a hard constraint); why each stage stopped
        (``"wide barrier (3 mm), u_b alone: ...; u_b alone: ...; joint: ..."``).
    parameters_optimized : bool
    search_barrier_mm : float
        Width of the skull barrier of the searched objective, mm.
    parameter_iterations_exact : int or None
        Iterations of the last stage over the parameters with the exact normaliser (all its
        rounds).
    """

    theta: np.ndarray
    logp_start: float
    logp_mode: float
    iterations: int
    message: str
    parameters_optimized: bool
    search_barrier_mm: float
    parameter_iterations_exact: int | None = None


@jax.jit
def _normaliser_gap(post: Posterior, surrogate, phi):
    """The exact normaliser less its surrogate at the free parameters ``phi``."""
    return log_normaliser(post, phi) - surrogate_normaliser(post, surrogate, phi)


def find_mode(post: Posterior, theta0, *, iterations: int = 1000, optimize_parameters: bool = True,
              exact: bool = False, rtol: float = 1e-8, maxiter: int = 1000,
              wide_barrier_mm: float | None = MODE_WIDE_BARRIER_MM) -> ModeSearch:
    """Maximise the log posterior from ``theta0`` (L-BFGS, JAX gradients through the solve).

    Optimises ``u_b`` and, with ``optimize_parameters``, the free elastic parameters too;
    otherwise the parameters stay at ``theta0``'s.  A first stage of ``iterations // 2``
    moves ``u_b`` alone under a skull barrier of ``wide_barrier_mm`` (where it is wider
    than the search's own): nodes that the images press toward the skull then slide along
    it at a distance instead of sticking in a pocket of the wall, from which the narrow
    barrier's search does not bring them back (docs: *Method*).
    The joint search then runs in two stages of
    ``iterations // 2`` L-BFGS iterations each: ``u_b`` alone at ``theta0``'s parameters,
    then ``u_b`` and the parameters together, these in the coordinates ``log(phi - r1)``
    (the result kept a relative margin 1e-3 inside the prior support).  Far from the mode
    the parameter gradient is meaningless, and the logit coordinates of the sampler
    (:func:`bayesreg.model.parameters.from_unconstrained`) saturate at the bounds: a first joint
    step can take a parameter to its upper bound and never come back.  A step into a hard
    constraint (``-inf``, also beyond ``r2``) lies outside the line search's domain and is
    shortened; if no feasible step gains, the search stops and says so in ``message``.
    Without a skull barrier in the model the search runs on the posterior plus a
    :data:`MODE_BARRIER_MM` barrier (:func:`bayesreg.mesh.constraints.skull_barrier`): on the hard
    wall alone the line search stalls as soon as the gradient points into the skull, while
    the barrier's maximum is strictly feasible and within the barrier of the constrained
    one; the chains sample the model as given.  Likewise against inverted elements: the
    objective has :func:`bayesreg.mesh.constraints.inversion_barrier` below the volume ratio
    :data:`MODE_VOLUME_RATIO` (on the hard ``J > 0`` alone a step toward the mode would
    crush an element and stall there).  Where L-BFGS's line search gives up, a backtracking
    gradient step is taken and L-BFGS starts afresh.  Each stage also stops where it stalls:
    less than :data:`MODE_STALL_NATS` gained over :data:`MODE_STALL_ITERATIONS` iterations
    (a crawl along a ridge, far below the chains' spread).  The barrier's own wall
    (:func:`bayesreg.mesh.constraints.skull_barrier`) is off in the search: there the barrier's
    huge finite values shorten the step, where ``-inf`` would stop the search.  With
    ``exact`` the search runs without the normaliser (it depends on the parameters only),
    then the parameters alone are optimised with it, in rounds: each maximises the posterior
    with the normaliser's smooth surrogate built where the round starts
    (:func:`bayesreg.model.posterior.normaliser_surrogate`: exact there in value, its gradient
    close; an exact gradient costs a selected inversion per step), at most 100 steps, until a round
    moves no parameter by more than 0.1% (at most :data:`SURROGATE_ROUNDS`).  A round is kept
    only where the exact ``log p`` did not fall (beyond the solves' noise): far from its
    centre the surrogate's quadratic part grows without bound, and a round that followed it
    there is undone and the parameters are optimised with the exact gradient from that
    round's start.  The mode's ``log p`` is the exact one.  With every node sampled (no interior,
    ``model.interior: sample``) the whole search runs with the surrogate built at
    ``theta0``'s parameters (without any normaliser the whole ``K``'s energy drives the
    parameters onto their lower edge), then the same rounds.  The per-element model, which
    has no surrogate, takes the exact normaliser's gradient.

    Parameters
    ----------
    post : Posterior
    theta0 : (dim,) array
        Start, inside every hard constraint.
    iterations : int
        L-BFGS iterations in all (split between the stages).
    optimize_parameters : bool
        Optimise the free elastic parameters too.
    exact : bool
        The posterior includes the exact normaliser of the elastic prior.
    rtol, maxiter
        The CG solve's tolerance and cap.
    wide_barrier_mm : float or None
        The first stage's barrier width (mm); ``None``: no such stage.

    Returns
    -------
    ModeSearch

    Raises
    ------
    ValueError
        ``theta0`` violates a hard constraint (skull, inverted element).
    """
    search_barrier = post.barrier_width
    if search_barrier == 0.0:
        search_barrier = MODE_BARRIER_MM
        post = with_skull_barrier(post, search_barrier)
    # the barrier's own wall off: its huge finite values make the line search step back,
    # where -inf would stop the search (the sampled posterior keeps the wall)
    post = post._replace(skull=post.skull._replace(barrier_wall=jnp.asarray(False)))
    nb3 = post.n_displacement  # the displacements (u_b, and a discrepancy d if any), then phi
    theta0 = np.asarray(theta0, dtype=np.float64)
    zeros = jnp.zeros((post.op.n_interior, 3))
    # the exact normaliser depends on lam, mu only: u_b (and the parameters) are first
    # optimised without it, then the parameters alone with it (below)
    # every node sampled (model.interior: sample): without the normaliser the whole K's
    # energy drives the parameters onto their lower edge: with it (its surrogate)
    exact_joint = exact and post.op.n_interior == 0
    volumes0 = element_volumes(post.nodes, post.tets)

    def plain(theta, guess, data):
        """The model with a skull barrier of ``data[0]`` mm (traced: the wide stage and the
        others share one compiled step), plus the barrier against inverted elements."""
        skull = post.skull._replace(barrier_width=data[0])
        lp, aux = logdensity_fn(post._replace(skull=skull), rtol=rtol, maxiter=maxiter)(theta, guess)
        u = nodal_displacement(post, theta, aux.interior)
        return lp + inversion_barrier(post.nodes + u, post.tets, volumes0, MODE_VOLUME_RATIO), aux
    grouped = post.normaliser.grounded.unit is not None

    def with_normaliser(theta, guess, data):
        """``log p`` with the normaliser.  With ``data = (width, surrogate, on, exact)``
        (``on``, ``exact``: ``()`` bools; all traced, so that every stage, round and the exact
        search share one compiled step): the exact normaliser where ``exact`` (a
        ``lax.cond``: its factorisations run only then), else its surrogate where ``on`` and
        none elsewhere.  Where ``data`` is ``(width,)`` (no surrogate: the per-element model),
        the exact one."""
        lp, aux = plain(theta, guess, data)
        phi = split_position(post, theta)[1]
        if len(data) == 1:
            return add_normaliser(lp, log_normaliser(post, phi)), aux
        _, surrogate, on, exact_now = data
        ln = jax.lax.cond(exact_now, lambda: log_normaliser(post, phi),
                          lambda: jnp.where(on, surrogate_normaliser(post, surrogate, phi), 0.0))
        return add_normaliser(lp, ln), aux

    joint = optimize_parameters
    free = slice(0, post.dim if joint else nb3)

    steps = {}  # one jitted L-BFGS step (and its solver) per objective, shared by its searches

    def maximise(logdensity, theta, sl, maxiter, data):
        """L-BFGS (optax, zoom line search) over ``theta[sl]``, the rest of ``theta`` held.

        The rest is held by a mask (``stop_gradient`` outside ``sl``): with zero gradient
        components L-BFGS's directions have zero components there, so the search is the one
        over ``theta[sl]`` alone, and the searches of one objective over different slices
        share one compiled step.

        A step into a hard constraint (``log p = -inf``) is outside the domain for the line
        search, which shortens it (a line search fed a huge value with a zero gradient
        there, as SciPy's L-BFGS-B's, collapses and reports convergence far from the
        mode).  ``data`` is passed to ``logdensity`` as its third argument (traced: one
        compilation for every ``data`` of one structure)."""
        if logdensity not in steps:
            solver = optax.lbfgs()

            @jax.jit
            def step(x, state, mask, data):
                def neg(y):
                    y = jnp.where(mask, y, jax.lax.stop_gradient(y))
                    return -logdensity(y, zeros, data)[0]

                v, g = optax.value_and_grad_from_state(neg)(x, state=state)
                upd, state = solver.update(g, state, x, value=v, grad=g, value_fn=neg)
                return optax.apply_updates(x, upd), state, v, g

            @jax.jit
            def value(y, data):  # compiled only if a gradient step is needed
                return -logdensity(y, zeros, data)[0]

            steps[logdensity] = step, solver, value
        step, solver, value = steps[logdensity]
        mask = np.zeros(len(theta), bool)
        mask[sl] = True
        step = partial(step, mask=jnp.asarray(mask), data=data)

        def gradient_step(x, v, g):
            """Backtracking (Armijo) along ``-g`` from a step that moves the largest
            coordinate by 1 (mm or log units): the point, or ``None``."""
            g = np.where(mask, np.asarray(g), 0.0)
            if not np.all(np.isfinite(g)):  # no direction to search along
                return None
            gg, t = float(g @ g), 1.0 / max(float(np.abs(g).max()), 1e-300)
            for _ in range(60):
                y = jnp.asarray(np.asarray(x) - t * g)
                f = float(value(y, data))
                if np.isfinite(f) and f <= v - 1e-4 * t * gg:
                    return y, f
                t *= 0.5
            return None

        x = jnp.asarray(theta)
        state = solver.init(x)
        # optax's initial state holds weakly typed scalars that its update returns strongly
        # typed (same dtypes): made strong here so that `step` compiles once, not twice
        state = jax.tree.map(lambda a: jnp.asarray(a, dtype=a.dtype), state)
        best_x, best_f, message, nit = x, np.inf, f"reached {maxiter} iterations", 0
        fallbacks, history = 0, []  # best_f after each iteration
        for nit in range(1, maxiter + 1):
            history.append(best_f)
            if nit > MODE_STALL_ITERATIONS and \
                    history[-1 - MODE_STALL_ITERATIONS] - best_f < MODE_STALL_NATS:
                message = (f"stalled: gained < {MODE_STALL_NATS:g} nats over the last "
                           f"{MODE_STALL_ITERATIONS} iterations")
                nit -= 1  # (this one not run)
                break
            x_new, state, v, g = step(x, state)
            v = float(v)  # the value at x
            if nit == 1:  # the start's value from the first step (no separate compilation of neg)
                start = -v
                if not np.isfinite(start):
                    raise ValueError("the central start violates a hard constraint (skull, inverted element)")
                best_f = v
            if np.isfinite(v) and v <= best_f:
                best_x, best_f = x, v
            f_new = float(optax.tree.get(state, "value"))
            if not np.isfinite(f_new):
                message = "line search found no feasible step"
                break
            x = x_new
            if f_new < best_f:
                best_x, best_f = x, f_new
            g_norm = float(jnp.linalg.norm(g))
            if f_new == v and g_norm > 1e-8:
                # L-BFGS's line search gave up (a stiff barrier or a hard constraint along
                # its direction): a backtracking gradient step, then L-BFGS afresh
                found = gradient_step(x, v, g)
                if found is None:
                    message = "no step: no feasible decrease along the gradient (a hard constraint)"
                    break
                x, f_new = found
                fallbacks += 1
                if f_new < best_f:
                    best_x, best_f = x, f_new
                state = jax.tree.map(lambda a: jnp.asarray(a, dtype=a.dtype), solver.init(x))
                continue
            if abs(v - f_new) <= 1e-10 * max(abs(f_new), 1.0) or g_norm <= 1e-8:
                message = "converged: relative reduction <= 1e-10 or gradient norm <= 1e-8"
                break
        out = theta.copy()
        out[sl] = np.asarray(best_x)[sl]  # (the rest unchanged: held by the mask)
        if fallbacks:
            message += f" ({fallbacks} gradient steps where the line search gave up)"
        return out, start, SimpleNamespace(fun=best_f, nit=nit, message=message)

    # the parameters move in the coordinates x = log(phi - r1) (the same objective, no
    # Jacobian: this is the mode over phi): positive by construction, a step beyond r2 is
    # -inf (outside the line search's domain), and unlike the sampler's logit coordinates
    # the gradient does not vanish near the upper bound
    lo, hi = np.maximum(np.asarray(post.prior.r1), 0.0), np.asarray(post.prior.r2)
    margin = 1e-3

    def in_log(logdensity):
        def f(x, guess, data):
            phi = lo + jnp.exp(x[nb3:])
            return logdensity(jnp.concatenate([x[:nb3], phi]), guess, data)
        return f

    def clip(phi):  # parameters kept the relative margin inside their support
        return np.clip(phi, lo + margin * (hi - lo), hi - margin * (hi - lo))

    def to_log(theta):
        return np.concatenate([theta[:nb3], np.log(clip(theta[nb3:]) - lo)])

    def to_theta(x):
        return np.concatenate([x[:nb3], clip(lo + np.exp(x[nb3:]))])

    iters = iterations
    x = to_log(theta0)
    width = jnp.asarray(float(search_barrier))
    objective, data = in_log(plain), (width,)
    normalised = in_log(with_normaliser)
    surrogates = exact and grouped and post.n_free
    if surrogates:  # one objective for every stage: the surrogate (at theta0's parameters) on or off
        objective = normalised
        data = (width, normaliser_surrogate(post, to_theta(x)[nb3:]), jnp.asarray(exact_joint),
                jnp.asarray(False))
    elif exact_joint:
        objective = normalised
    wide = wide_barrier_mm is not None and wide_barrier_mm > search_barrier
    pre, nit = "", 0
    if wide:  # stage 0: u_b alone under the wide barrier
        data_w = (jnp.asarray(float(wide_barrier_mm)),) + data[1:]
        x, start0, res0 = maximise(objective, x, slice(0, nb3), max(iters // 2, 1), data_w)
        pre, nit = f"wide barrier ({wide_barrier_mm:g} mm), u_b alone: {res0.message} ({res0.nit} its); ", res0.nit
    if joint and post.n_free:  # stage 1: u_b alone at theta0's parameters
        x, start, res1 = maximise(objective, x, slice(0, nb3), max(iters // 2, 1), data)
        x, _, res = maximise(objective, x, free, max(iters - iters // 2, 1), data)
        nit += res1.nit + res.nit
        res.message = f"{pre}u_b alone: {res1.message} ({res1.nit} its); joint: {res.message}"
    else:
        x, start, res = maximise(objective, x, free, iters, data)
        nit += res.nit
        res.message = pre + res.message
    if wide:
        start = start0
    logp_mode, exact_its = -float(res.fun), None
    if joint and exact and post.n_free:
        # the parameters alone with the normaliser: rounds of its surrogate built where each
        # starts, each kept only where the exact log p did not fall (the surrogate is exact at
        # its centre, and its quadratic part grows without bound far from there); otherwise, and
        # for the per-element model, the exact gradient from that round's start
        exact_its, sl_p, exact_search = 0, slice(nb3, post.dim), not surrogates
        for _ in range(SURROGATE_ROUNDS if surrogates else 0):
            x = to_log(to_theta(x))  # inside the margins: where the surrogate is built
            before = to_theta(x)[nb3:]
            data = (width, normaliser_surrogate(post, before), jnp.asarray(True), jnp.asarray(False))
            x_new, lp_start, res_p = maximise(normalised, x, sl_p, 100, data)
            exact_its += int(res_p.nit)
            # exact log p at both ends: the surrogate's values with it swapped for the exact
            # normaliser (no program compiled for the whole exact log-density)
            lp_start += float(_normaliser_gap(post, data[1], jnp.asarray(before)))
            phi_new = jnp.asarray(lo + np.exp(np.asarray(x_new)[nb3:]))
            lp_new = -float(res_p.fun) + float(_normaliser_gap(post, data[1], phi_new))
            # fell by more than the solves' noise (a round that barely moves can lose 1e-10
            # of log p to CG's tolerance), or NaN (parameters CHOLMOD is not given): undone
            if not lp_new >= lp_start - 1e-8 * max(abs(lp_start), 1.0):
                exact_search = True
                break
            x, logp_mode = x_new, lp_new
            if np.max(np.abs(np.log(to_theta(x)[nb3:] / before))) < 1e-3:
                break
        # the exact normaliser: on the surrogates' step (one compiled program whether or not
        # the rounds fall back), or the per-element model's own
        exact_data = data[:2] + (jnp.asarray(True), jnp.asarray(True)) if surrogates else (width,)
        if exact_search:  # (the rounds' budget left, or one round's for the per-element model)
            budget = max(100, 100 * SURROGATE_ROUNDS - exact_its) if surrogates else 100
            x, _, res_p = maximise(normalised, x, sl_p, budget, exact_data)
            exact_its += int(res_p.nit)
            logp_mode = -float(res_p.fun)
        inside = to_log(to_theta(x))
        if not np.array_equal(inside, np.asarray(x)):  # a parameter beyond its margin: the
            x = inside  # exact log p where the search's point is returned
            logp_mode = -float(steps[normalised][2](jnp.asarray(x), exact_data))
    theta = to_theta(x) if joint else np.concatenate([x[:nb3], theta0[nb3:]])
    return ModeSearch(theta, float(start), logp_mode, int(nit), str(res.message), bool(joint),
                      float(search_barrier), exact_its)

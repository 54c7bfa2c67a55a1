"""Gradient kernels in Gibbs with the elastic block (bayesreg.sampling.kernels.gibbs) on known targets."""

import numpy as np
import pytest

import arviz as az
import jax
import jax.numpy as jnp

from bayesreg.sampling.chains import build_chunk
from bayesreg.sampling.kernels import gibbs as gk
from bayesreg.sampling.kernels.collapsed import collapsed_proposal
from bayesreg.sampling.kernels.target import make_target
from helpers import (
    assert_moments, D, gaussian_target, M_ETA, S, sample_gibbs, SD_ETA, toy_moments,
    toy_target)


@pytest.mark.parametrize("kind,adapt_mass", [("mala", True), ("hmc", True), ("nuts", True), ("nuts", False)])
def test_gibbs_gradient_kernel_samples_a_known_joint(kind, adapt_mass):
    """Means and variances of u and eta within 5 Monte Carlo standard errors, each from
    ArviZ's ESS of the quantity averaged (:func:`helpers.assert_moments`)."""
    rng = np.random.default_rng(0)
    x0 = np.concatenate([rng.normal(size=(4, D)), rng.normal(M_ETA, SD_ETA, size=(4, 1))], axis=1)
    res = sample_gibbs(jax.random.key(1), toy_target(), x0, jnp.zeros((1, 3)), kind=kind,
                          step_size=0.3, eta_scale=0.5, num_integration_steps=8, warmup_steps=600,
                          adapt_mass=adapt_mass, elastic_moves=1 if adapt_mass else 3,
                          max_draws=1500, min_draws=1500, chunk_draws=100, thinning=1, progress=False)
    draws = res.positions  # (C, n, D + 1)
    assert res.divergences.mean() < 0.01  # the toy is a mild funnel: rare divergences allowed
    mean_true, var_true, fourth_true = toy_moments()
    for j in range(D + 1):
        x = draws[..., j]
        ess = float(az.ess(x, method="bulk"))
        assert ess > 50, (kind, j, ess)
        assert_moments(x, mean_true[j], var_true[j], fourth_true[j], n_se=5.0, what=(kind, j))
    acc = res.acceptance.reshape(-1, 2).mean(axis=0)
    assert 0.25 < acc[0] < 0.99 and 0.1 < acc[1] < 0.7, acc  # targets 0.57 (MALA), 0.8; 0.3
    step, inv_mass, eta_scale, collapsed, surrogate_center = res.sigma
    assert step.shape == (4,) and inv_mass.shape == (4, D) and eta_scale.shape == (4, 1, 1)
    assert surrogate_center.shape == (4, 0)  # no surrogate rebuilt
    if not adapt_mass:
        np.testing.assert_array_equal(inv_mass, 1.0)
    assert np.all(res.grad_evals >= 1)


def test_joint_nuts_samples_the_known_joint():
    """NUTS over ``u`` and ``eta`` together (a joint target: no elastic block) reaches the
    toy's moments within 5 Monte Carlo standard errors, as the Gibbs kernel does, and names
    its one block "joint"."""
    from bayesreg.sampling.kernels.target import joint_target

    rng = np.random.default_rng(0)
    x0 = np.concatenate([rng.normal(size=(4, D)), rng.normal(M_ETA, SD_ETA, size=(4, 1))], axis=1)
    tg = joint_target(toy_target(), center_eta=jnp.array([M_ETA]), eta_scale=SD_ETA,
                      log_jacobian=lambda eta: jnp.zeros(()))
    res = sample_gibbs(jax.random.key(1), tg, x0, jnp.zeros((1, 3)), kind="nuts", step_size=0.3,
                          eta_scale=np.zeros(0), warmup_steps=600, max_draws=1500, min_draws=1500,
                          chunk_draws=100, thinning=1, progress=False)
    assert res.info.blocks == ("joint",) and res.acceptance.shape[-1] == 1
    assert res.divergences.mean() < 0.01
    mean_true, var_true, fourth_true = toy_moments()
    for j in range(D + 1):
        assert_moments(res.positions[..., j], mean_true[j], var_true[j], fourth_true[j], n_se=5.0,
                       what=("joint", j))
    # the stored log-density is the natural one: the toy's, whose Jacobian is 0
    lp = jax.vmap(jax.vmap(lambda x: toy_target().evaluate(x[:D] / jnp.asarray(S), x[D:], None,
                                                           -D * x[D])[1]))(jnp.asarray(res.positions))
    np.testing.assert_allclose(res.logdensity, np.asarray(lp), rtol=1e-10)


def test_a_surrogate_normaliser_corrected_per_transition_samples_the_exact_joint():
    """Joint NUTS whose trajectories see a wrong surrogate of the normaliser (another slope
    and a wiggle: alone it shifts ``eta``'s mean by about 9 Monte Carlo standard errors)
    reaches the exact toy's moments within 5 once each trajectory's end is accepted with
    ``min(1, exp(Delta' - Delta))``, ``Delta`` the exact normaliser less the surrogate (a
    surrogate transition); the correction is the second block, "normaliser", with an
    acceptance below one, and the stored log-density is the exact natural one."""
    from bayesreg.sampling.kernels.target import joint_target

    rng = np.random.default_rng(0)
    x0 = np.concatenate([rng.normal(size=(4, D)), rng.normal(M_ETA, SD_ETA, size=(4, 1))], axis=1)

    def surrogate(eta):
        return -0.5 * D * eta[0] + 0.3 * jnp.sin(5.0 * eta[0])

    tg = joint_target(toy_target(), center_eta=jnp.array([M_ETA]), eta_scale=SD_ETA,
                      log_jacobian=lambda eta: jnp.zeros(()), surrogate=surrogate)
    res = sample_gibbs(jax.random.key(1), tg, x0, jnp.zeros((1, 3)), kind="nuts", step_size=0.3,
                          eta_scale=np.zeros(0), warmup_steps=600, max_draws=1500, min_draws=1500,
                          chunk_draws=100, thinning=1, progress=False)
    assert res.info.blocks == ("joint", "normaliser") and res.acceptance.shape[-1] == 2
    acc = res.acceptance[..., 1].mean()
    assert 0.5 < acc < 0.99, acc
    mean_true, var_true, fourth_true = toy_moments()
    for j in range(D + 1):
        assert_moments(res.positions[..., j], mean_true[j], var_true[j], fourth_true[j], n_se=5.0,
                       what=("surrogate", j))
    lp = jax.vmap(jax.vmap(lambda x: toy_target().evaluate(x[:D] / jnp.asarray(S), x[D:], None,
                                                           -D * x[D])[1]))(jnp.asarray(res.positions))
    np.testing.assert_allclose(res.logdensity, np.asarray(lp), rtol=1e-10)


def test_a_failed_evaluation_at_the_chains_own_parameters_moves_nothing_and_is_counted():
    """The elastic moves compare each proposal with the chain's parameters re-evaluated at
    its new ``u_b``; if that evaluation fails (``-inf``, not ok), no proposal is accepted
    against it (a finite proposal over ``-inf`` would be a log-ratio of ``+inf``) and the
    failure is counted."""
    rng = np.random.default_rng(3)
    x0 = np.concatenate([rng.normal(size=(2, D)), np.full((2, 1), M_ETA)], axis=1)
    target = toy_target()

    starts = jnp.asarray(x0[:, :D] / S)

    def evaluate(w, eta, interior, ln):
        lp, lnat, interior, its, ok = target.evaluate(w, eta, interior, ln)
        # fails at the chains' starting parameters once u_b has left its start (so not in
        # the check of the starts), and nowhere else
        bad = (eta[0] == M_ETA) & ~jnp.any(jnp.all(w[None] == starts, axis=1))
        return jnp.where(bad, -jnp.inf, lp), jnp.where(bad, -jnp.inf, lnat), interior, its, ok & ~bad

    # a small step: the first u_b moves are accepted (fixed seed), so every re-evaluation fails
    res = sample_gibbs(jax.random.key(2), target._replace(evaluate=evaluate), x0,
                          jnp.zeros((1, 3)), kind="mala", step_size=0.05, eta_scale=0.5,
                          warmup_steps=0, max_draws=10, min_draws=10, chunk_draws=10, thinning=1,
                          progress=False)
    assert np.all(res.positions[..., D] == M_ETA)  # never moved
    assert np.all(res.solve_failures >= 1)  # one per transition at least


@pytest.mark.parametrize("jitter", [False, True])
def test_hmc_jitter_breaks_a_periodic_trajectory(jitter):
    """On ``N(0, I)`` with ``L`` leapfrog steps of ``eps = 2 sin(pi / 2L)`` the leapfrog map
    to the power ``L`` is exactly ``-I``: every fixed-length transition maps ``x`` to ``-x``
    (accepted, energy conserved), so the chain never leaves ``{x0, -x0}``.  With the number
    of steps drawn from ``1 .. 2L - 1`` the chain samples the target: mean and variance within
    Monte Carlo error, and the drawn lengths cover that range with mean ``L``."""
    dim, n_leap, n_steps = 8, 8, 3000
    target = gaussian_target(dim)
    kernel = gk.build_kernel(target, "hmc", num_integration_steps=n_leap, jitter_integration_steps=jitter)
    x0 = jnp.linspace(0.5, 2.0, dim)
    state, cache = gk.init(target, x0, jnp.zeros((1, 3)))
    params = gk.GibbsParams(jnp.asarray(2 * np.sin(np.pi / (2 * n_leap))), jnp.ones(dim), jnp.zeros((0, 0)))

    def step(carry, key):
        st, ca = carry
        st, info, ca = kernel.step(key, st, params, ca)
        return (st, ca), (st.position, info.grad_evals)

    _, (xs, n) = jax.jit(lambda k: jax.lax.scan(step, (state, cache), jax.random.split(k, n_steps)))(
        jax.random.key(0))
    xs, n = np.asarray(xs), np.asarray(n)
    if not jitter:
        np.testing.assert_array_equal(n, n_leap)
        np.testing.assert_allclose(np.abs(xs), np.broadcast_to(np.asarray(x0), xs.shape), rtol=1e-9)
        return
    assert n.min() == 1 and n.max() == 2 * n_leap - 1
    assert abs(n.mean() - n_leap) < 5 * np.sqrt((4 * n_leap**2 - 4) / 12 / n_steps)  # uniform on 1..2L-1
    ess = min(float(az.ess(xs[None, :, j], method="bulk")) for j in range(dim))
    assert ess > 300, ess
    for j in range(dim):  # N(0, 1): fourth central moment 3
        assert_moments(xs[None, :, j], 0.0, 1.0, 3.0, n_se=5.0, what=j)


@pytest.mark.heavy  # (the same property for the random walk: tests/test_rwmh.py)
def test_preconditioned_gibbs_kernel_gives_the_draws_of_block_jacobi(small):
    """NUTS-in-Gibbs with the dense preconditioner (built at each chunk start, kept through the
    cache rebuilds after accepted elastic moves) takes the chains where block Jacobi takes
    them: its solves (the elastic moves' and, without the condensation, the trajectories')
    meet the same tolerance, in fewer iterations."""
    condensed = False  # every solve of the kernel preconditioned

    _, post, theta = small
    nb3 = 3 * post.n_boundary
    factor = np.full(nb3, 0.05)
    x0 = np.tile(theta, (2, 1))
    x0[:, :nb3] += 0.02 * np.random.default_rng(4).normal(size=(2, nb3))
    params = gk.GibbsParams(jnp.full(2, 0.3), jnp.ones((2, nb3)), jnp.tile(0.05 * jnp.eye(post.n_free), (2, 1, 1)))
    outs, its = [], []
    for precondition in (False, True):
        tg = make_target(post, center_u=np.zeros(nb3), factor=factor, exact=False, condensed=condensed,
                         rtol=1e-12, precondition=precondition)
        kernel = gk.build_kernel(tg, "nuts", max_num_doublings=3, elastic_moves=3)
        states = jax.jit(jax.vmap(lambda x: gk.init(tg, x, jnp.zeros((post.op.n_interior, 3)))[0]))(jnp.asarray(x0))
        if precondition:
            assert kernel.init_cache(jax.tree.map(lambda a: a[0], states)).precond is not None
        _, out = build_chunk(kernel, 2, 1, 2, method="threads").run(
            jax.random.split(jax.random.key(3), 2), states, params)
        outs.append(out)
        its.append(float(np.asarray(out[4]).mean()))
    (plain, fast) = outs
    np.testing.assert_allclose(np.asarray(fast[0]), np.asarray(plain[0]), rtol=1e-7, atol=1e-9)  # positions
    np.testing.assert_allclose(np.asarray(fast[2]), np.asarray(plain[2]), rtol=1e-9)  # log p
    assert np.asarray(plain[3])[..., 1].max() > 0  # elastic moves accepted (the cache rebuilt)
    assert its[1] < 0.5 * its[0] and np.asarray(fast[5]).sum() == 0  # fewer iterations, no failure


def _toy_conditional(shift=0.0, scale=1.0):
    """The toy's ``u | eta`` as the collapsed moves take it: exact for ``shift=0, scale=1``
    (``N(A eta, e^(2 eta) S^2)``), else a deliberately wrong Gaussian."""
    from helpers import A

    def conditional(eta, _tau=None):
        mean = jnp.full(D, A * eta[0] + shift)
        return mean, jnp.diag(1.0 / (scale * jnp.asarray(S) * jnp.exp(eta[0])))

    return conditional


@pytest.mark.parametrize("shift,scale", [(0.0, 1.0), (0.7, 2.0)])
def test_collapsed_moves_keep_the_joint(shift, scale):
    """Collapsed moves (u carried along by a Gaussian u | eta, the Jacobian in the
    acceptance) leave the toy's joint invariant whether that Gaussian is exact or wrong:
    moments within 5 Monte Carlo standard errors; with the exact one eta mixes better than
    with the random walk given u alone."""
    rng = np.random.default_rng(0)
    x0 = np.concatenate([rng.normal(size=(4, D)), rng.normal(M_ETA, SD_ETA, size=(4, 1))], axis=1)
    target = toy_target()._replace(conditional=_toy_conditional(shift, scale))
    common = dict(kind="nuts", step_size=0.3, eta_scale=0.5, warmup_steps=300, elastic_moves=1,
                  max_draws=1000, min_draws=1000, chunk_draws=100, progress=False)
    res = sample_gibbs(jax.random.key(2), target, x0, jnp.zeros((1, 3)), collapsed_moves=2,
                          **common)
    mean_true, var_true, fourth_true = toy_moments()
    for j in range(D + 1):
        assert_moments(res.positions[..., j], mean_true[j], var_true[j], fourth_true[j], n_se=5.0,
                       what=("collapsed", shift, j))
    acc = res.acceptance.reshape(-1, 3).mean(axis=0)
    assert acc.shape == (3,) and 0.05 < acc[2] < 0.9, acc
    assert res.info.blocks == ("u_b", "elastic", "collapsed")
    assert res.sigma[3].shape == (4, 1, 1)
    if shift == 0.0:
        base = sample_gibbs(jax.random.key(2), toy_target(), x0, jnp.zeros((1, 3)), **common)
        ess_c = float(az.ess(res.positions[..., D], method="bulk"))
        ess_b = float(az.ess(base.positions[..., D], method="bulk"))
        assert ess_c > 1.5 * ess_b, (ess_c, ess_b)


def test_collapsed_moves_need_a_conditional():
    with pytest.raises(ValueError, match="collapsed"):
        gk.build_kernel(toy_target(), "nuts", collapsed_moves=1)


def _shifted_gaussian(mean):
    """``u ~ N(mean, I)``, no elastic parameters: a target that depends on data."""
    from bayesreg.sampling.kernels.target import Cache, Target

    def u_lp(w, eta, cache, interior):
        return -0.5 * jnp.sum((w - mean) ** 2)

    return Target(u_lp, lambda w, eta, c, i: (u_lp(w, eta, c, i), i, jnp.asarray(0), jnp.asarray(True)),
                  lambda w, eta, i, ln: (u_lp(w, eta, None, i), u_lp(w, eta, None, i), i,
                                         jnp.asarray(0), jnp.asarray(True)),
                  lambda eta: jnp.zeros(()),
                  lambda eta, ln: Cache(jnp.zeros((0,)), jnp.asarray(ln, jnp.float64)),
                  lambda w, eta: w, lambda theta: (theta, jnp.zeros((0,))), 0)


def test_chains_with_their_own_data_sample_their_own_targets_in_one_program():
    """Per-chain data (``chain_data``, as the calibration's replicas use): chain ``c`` samples
    ``N(m_c, I)`` (moments within 5 Monte Carlo standard errors), gives the draws a run on
    ``m_c`` alone gives that chain (same key, same starts), and ``refresh`` rewrites the
    chains' data once, after the warm-up's last chunk, and never while sampling."""
    from bayesreg.sampling.driver import SamplerCheckpoint, sample

    means = np.array([[-3.0, 1.0], [0.0, 0.0], [2.0, -1.0], [5.0, 4.0]])
    data = {"mean": jnp.asarray(means), "marker": jnp.zeros((4, 2))}
    x0 = np.random.default_rng(0).normal(size=(4, 2))

    def refresh(state):
        return state._replace(data={**state.data, "marker": state.position})

    common = dict(interior0=jnp.zeros((1, 3)), kind="nuts", step_size=0.5, eta_scale=np.zeros(0))
    run = dict(warmup_steps=200, max_draws=1000, min_draws=1000, chunk_draws=100, progress=False,
               chain_method="sequential")
    alg = gk.as_algorithm(lambda d: _shifted_gaussian(d["mean"]), chain_data=data,
                          refresh=refresh, **common)
    warm_end = []
    res = sample(jax.random.key(3), alg, x0, on_chunk=lambda cp, out: warm_end.append(cp)
                 if out is None else None, **run)
    assert isinstance(warm_end[0], SamplerCheckpoint) and len(warm_end) == 1
    after_warmup = warm_end[0].states
    np.testing.assert_array_equal(after_warmup.data["marker"], after_warmup.position)
    np.testing.assert_array_equal(res.final_states.data["marker"], after_warmup.position)
    np.testing.assert_array_equal(res.final_states.data["mean"], means)
    for c in range(4):
        for j in range(2):
            assert_moments(res.positions[c:c + 1, :, j], means[c, j], 1.0, 3.0, what=(c, j))
    one = sample(jax.random.key(3), gk.as_algorithm(_shifted_gaussian(jnp.asarray(means[1])),
                                                     **common), x0, **run)
    np.testing.assert_allclose(one.positions[1], res.positions[1], rtol=0, atol=1e-10)
    with pytest.raises(ValueError, match="data for \\[4\\] chains, the starts are 3"):
        sample(jax.random.key(3), alg, x0[:3], **run)
    with pytest.raises(ValueError, match="chain_data goes with"):
        gk.as_algorithm(_shifted_gaussian(0.0), chain_data=data, **common)


Y_OBS, SD_OBS = 3.0, 0.5  # an observation of eta + d: d follows eta (a ridge)


def _mixture_toy(a=3.0, b=1.0, scales=(1.0, 2.0, 4.0, 2.0)):
    """The toy with a Student-t "discrepancy" ``d`` (``df = 2a``, scale ``sqrt(b / a)``)
    that every ``u_j`` sees, ``u_j | eta, d ~ N(A eta + d, (S_j e^eta)^2)`` (``S`` the
    ``scales``), and an observation ``Y_OBS ~ N(eta + d, SD_OBS^2)``, so that ``d`` follows
    ``eta`` along a ridge, as the model discrepancy follows the elastic parameters.  The
    position is ``[d, u, eta]``; the target's mixture is ``d``'s scale mixture (``tau | d ~
    Gamma(a + 1/2, b + d^2 / 2)``) and its conditional the exact Gaussian of ``x = [d, u]``
    given ``eta`` and ``tau``.  Marginals of ``(eta, d)``: :func:`_mixture_moments`."""
    from helpers import A
    from bayesreg.sampling.kernels.target import Mixture

    base = toy_target()
    sc = jnp.asarray(scales)
    f = jnp.r_[1.0, sc]
    shape = a + 0.5

    def lp(w, eta):
        x = f * w
        d, u = x[0], x[1:]
        return (-0.5 * jnp.sum(((u - A * eta[0] - d) / (sc * jnp.exp(eta[0]))) ** 2)
                - 0.5 * ((Y_OBS - eta[0] - d) / SD_OBS) ** 2
                - 0.5 * ((eta[0] - M_ETA) / SD_ETA) ** 2 - shape * jnp.log1p(d * d / (2 * b)))

    def evaluate(w, eta, interior, ln):
        v = lp(w, eta) + ln
        return v, v, interior, jnp.asarray(0), jnp.asarray(True)

    def conditional(eta, tau):
        p = 1.0 / (sc * jnp.exp(eta[0])) ** 2
        p_dd = jnp.sum(p) + tau + 1.0 / SD_OBS**2
        prec = jnp.block([[p_dd[None, None], -p[None, :]], [-p[:, None], jnp.diag(p)]])
        lin = jnp.r_[(Y_OBS - eta[0]) / SD_OBS**2 - A * eta[0] * jnp.sum(p), A * eta[0] * p]
        chol = jnp.linalg.cholesky(prec)
        return jax.scipy.linalg.cho_solve((chol, True), lin), chol

    mixture = Mixture(
        draw=lambda key, x: jax.random.gamma(key, shape) / (b + 0.5 * x[0] ** 2),
        log_ratio=lambda x, tau: -0.5 * tau * x[0] ** 2 + shape * jnp.log1p(x[0] ** 2 / (2 * b)))
    return base._replace(
        u_logdensity=lambda w, eta, cache, interior: lp(w, eta),
        u_evaluate=lambda w, eta, cache, interior: (lp(w, eta), interior, jnp.asarray(0), jnp.asarray(True)),
        evaluate=evaluate, position=lambda w, eta: jnp.concatenate([f * w, eta]),
        coordinates=lambda theta: (theta[:D + 1] / f, theta[D + 1:]), conditional=conditional,
        mixture=mixture)


def _mixture_moments(a, b):
    """Mean, variance and fourth central moment of ``d`` and of ``eta`` under
    :func:`_mixture_toy` (the ``u`` integrate out), by quadrature on a 2-D grid."""
    from scipy.stats import norm, t

    eta = np.linspace(M_ETA - 10 * SD_ETA, M_ETA + 10 * SD_ETA, 1201)
    d = np.linspace(-12.0, 12.0, 4801)
    e, dd = np.meshgrid(eta, d, indexing="ij")
    p = (norm.pdf(e, M_ETA, SD_ETA) * t.pdf(dd, 2 * a, scale=np.sqrt(b / a))
         * norm.pdf(Y_OBS, e + dd, SD_OBS))
    p /= p.sum()
    out = []
    for v in (dd, e):
        m = np.sum(p * v)
        out.append((m, np.sum(p * (v - m) ** 2), np.sum(p * (v - m) ** 4)))
    return out


def _assert_mixture_moments(res, a, b):
    """Draws of :func:`_mixture_toy` (or :func:`_shift_toy`): the means and variances of
    ``d`` and ``eta`` within 5 Monte Carlo standard errors of their quadrature, the ``u``'s
    means at ``A E[eta] + E[d]``, the collapsed moves accepted neither never nor always."""
    from helpers import A

    (m_d, v_d, f_d), (m_e, v_e, f_e) = _mixture_moments(a, b)
    assert_moments(res.positions[..., 0], m_d, v_d, f_d, n_se=5.0, what="d")
    assert_moments(res.positions[..., D + 1], m_e, v_e, f_e, n_se=5.0, what="eta")
    for j in range(1, D + 1):
        x = res.positions[..., j]
        se = np.sqrt(x.var() / float(az.ess(x, method="mean")))
        assert abs(x.mean() - (A * m_e + m_d)) < 5 * se, (j, x.mean(), se)
    acc = res.acceptance.reshape(-1, 3).mean(axis=0)
    assert 0.05 < acc[2] < 0.95, acc


def test_collapsed_moves_at_a_drawn_discrepancy_precision_keep_the_student_marginal():
    """Collapsed moves of ``eta`` carrying ``[d, u]`` along a ridge (``d`` follows ``eta``),
    each transition's made at a precision ``tau`` of ``d`` drawn from its conditional and
    accepted against the log-density at that ``tau`` (the target's :class:`Mixture`), leave
    the joint invariant: the means and variances of ``d`` (a Student prior times a
    Gaussian) and ``eta`` within 5 Monte Carlo standard errors of their quadrature, the
    ``u``'s means at ``A E[eta] + E[d]``."""
    a, b = 3.0, 1.0
    rng = np.random.default_rng(0)
    x0 = np.concatenate([rng.normal(size=(4, D + 1)), rng.normal(M_ETA, SD_ETA, size=(4, 1))], axis=1)
    res = sample_gibbs(jax.random.key(5), _mixture_toy(a, b), x0, jnp.zeros((1, 3)), kind="nuts",
                       step_size=0.3, eta_scale=0.5, warmup_steps=300, elastic_moves=1,
                       collapsed_moves=4, max_draws=1500, min_draws=1500, chunk_draws=100,
                       progress=False)
    _assert_mixture_moments(res, a, b)


def test_a_collapsed_proposal_under_the_exact_conditional_accepts_by_the_parameters_marginal():
    """With the exact Gaussian of ``x = [d, u]`` given ``eta`` and ``tau``, a collapsed move's
    log acceptance ratio (the log-density ratio plus :func:`~bayesreg.sampling.kernels.collapsed.collapsed_proposal`'s correction:
    the Jacobian and the mixture's term) is that of the parameters' marginal at ``tau``
    whatever ``x``: for the ridge toy ``log N(eta; M, s^2) + log N(Y - eta; 0, 1/tau +
    SD_OBS^2)`` (``d`` integrated out in closed form).  Without the mixture's term the
    ratio would be the Student marginal's, which differs."""
    from scipy.stats import norm

    a, b = 1.0, 1.0
    target = _mixture_toy(a, b)

    def log_marginal(eta, tau):
        return norm.logpdf(eta, M_ETA, SD_ETA) + norm.logpdf(Y_OBS - eta, 0.0, np.sqrt(1 / tau + SD_OBS**2))

    def lz(w, eta):
        return float(target.evaluate(w, eta, None, target.log_norm(eta))[0])

    rng = np.random.default_rng(3)
    gaps = []
    for _ in range(5):
        x = jnp.asarray(np.r_[rng.normal(2.0, 1.0), rng.normal(size=D)])
        eta, eta_p = jnp.asarray(rng.normal(M_ETA, 0.2, 1)), jnp.asarray(rng.normal(M_ETA, 0.2, 1))
        tau = float(rng.gamma(2.0, 0.5))
        w, _ = target.coordinates(jnp.concatenate([x, eta]))
        mean, chol = target.conditional(eta, tau)
        w_p, mean_p, chol_p, log_corr = collapsed_proposal(target, w, eta, eta_p, tau, mean, chol)
        np.testing.assert_allclose(np.asarray(target.conditional(eta_p, tau)[0]), np.asarray(mean_p))
        ratio = lz(w_p, eta_p) - lz(w, eta) + float(log_corr)
        expected = log_marginal(float(eta_p[0]), tau) - log_marginal(float(eta[0]), tau)
        np.testing.assert_allclose(ratio, expected, rtol=1e-9, atol=1e-9)
        gaps.append(abs(float(target.mixture.log_ratio(target.position(w_p, eta_p)[:-1], tau)
                              - target.mixture.log_ratio(x, tau))))
    assert max(gaps) > 1e-2  # the mixture's term is not negligible in these moves


def _shift_toy(a=3.0, b=1.0):
    """:func:`_mixture_toy` with an "FE interior" ``eta`` (what the target's evaluations
    return as ``interior``) and the discrepancy ``d`` beside it (``Y_OBS`` sees ``eta + d``):
    the target's ``shift`` moves ``d``, so a move that carries the displacement keeps ``eta +
    d``."""
    base = _mixture_toy(a, b)

    def fe(eta):
        return jnp.full((1, 3), eta[0])

    def evaluate(w, eta, interior, ln):
        v = base.evaluate(w, eta, interior, ln)
        return v[:2] + (fe(eta),) + v[3:]

    def u_evaluate(w, eta, cache, interior):
        v = base.u_evaluate(w, eta, cache, interior)
        return (v[0], fe(eta)) + v[2:]

    return base._replace(evaluate=evaluate, u_evaluate=u_evaluate, conditional=None, mixture=None,
                         shift=lambda x, delta: x.at[0].add(delta[0, 0]))


def test_collapsed_moves_that_carry_the_displacement_keep_the_joint():
    """Collapsed moves of ``eta`` with ``carry="displacement"`` (``d`` takes up the "FE
    interior"'s change, :func:`_shift_toy`) leave the joint invariant: the means and
    variances of ``d`` and ``eta`` within 5 Monte Carlo standard errors of their quadrature,
    the ``u``'s means at ``A E[eta] + E[d]``."""
    a, b = 3.0, 1.0
    rng = np.random.default_rng(4)
    x0 = np.concatenate([rng.normal(size=(4, D + 1)), rng.normal(M_ETA, SD_ETA, size=(4, 1))], axis=1)
    res = sample_gibbs(jax.random.key(8), _shift_toy(a, b), x0, jnp.zeros((1, 3)), kind="nuts",
                       step_size=0.3, eta_scale=0.5, warmup_steps=300, elastic_moves=1,
                       collapsed_moves=4, carry="displacement", max_draws=1500, min_draws=1500,
                       chunk_draws=100, progress=False)
    _assert_mixture_moments(res, a, b)


def test_carrying_the_displacement_needs_a_target_that_can_shift_it():
    with pytest.raises(ValueError, match="Target.shift"):
        gk.build_kernel(toy_target(), "nuts", collapsed_moves=2, carry="displacement")
    with pytest.raises(ValueError, match="unknown carry"):
        gk.build_kernel(_shift_toy(), "nuts", collapsed_moves=2, carry="both")


def test_a_surrogate_rebuilt_after_the_warmup_where_the_chains_are_corrects_less_and_stays_exact():
    """A joint target whose surrogate is exact only near the point it was built at
    (``-D eta + 20 (eta - c)^2``), built first far in the tail (``c`` 4 sd above the mean):
    with :class:`~bayesreg.sampling.kernels.surrogate.SurrogateRebuild` the warm-up's end
    rebuilds it once, at the chains' median ``eta``, frozen with the tuned values (one
    centre for every chain, in ``run.json``'s description); the correction then accepts
    more than with the far surrogate kept, the moments are the exact toy's within 5 Monte
    Carlo standard errors, and a run resumed from the checkpoint written after the warm-up
    gives the same draws."""
    from bayesreg.sampling.driver import sample
    from bayesreg.sampling.kernels.surrogate import SurrogateRebuild
    from bayesreg.sampling.kernels.target import joint_target

    rng = np.random.default_rng(0)
    x0 = np.concatenate([rng.normal(size=(4, D)), rng.normal(M_ETA, SD_ETA, size=(4, 1))], axis=1)
    built = []

    def target_at(c):
        built.append(float(c[0]))
        return joint_target(toy_target(), center_eta=jnp.array([M_ETA]), eta_scale=SD_ETA,
                            log_jacobian=lambda eta: jnp.zeros(()),
                            surrogate=lambda eta: -D * eta[0] + 20.0 * (eta[0] - c[0]) ** 2)

    far = np.array([M_ETA + 4 * SD_ETA])
    run = dict(warmup_steps=600, max_draws=1500, min_draws=1500, chunk_draws=100, thinning=1,
               progress=False)
    alg = dict(kind="nuts", step_size=0.3, eta_scale=np.zeros(0))
    kept = sample_gibbs(jax.random.key(1), target_at(far), x0, jnp.zeros((1, 3)), **alg, **run)
    algorithm = gk.as_algorithm(target_at(far), jnp.zeros((1, 3)), **alg,
                                surrogate=SurrogateRebuild(1, target_at))
    ckpts = []
    res = sample(jax.random.key(1), algorithm, x0, **run,
                 on_chunk=lambda ck, out: ckpts.append(ck) if out is None else None)
    center = res.sigma[4]
    assert center.shape == (4, 1) and np.all(center == center[0])
    assert built[2:] == [float(center[0, 0])]  # rebuilt once, where the chains were
    assert abs(center[0, 0] - M_ETA) < 3 * SD_ETA
    assert res.info.adapted["normaliser_surrogate_center"] == [float(center[0, 0])]
    acc_kept, acc = kept.acceptance[..., 1].mean(), res.acceptance[..., 1].mean()
    assert acc > 0.4 and acc > 3 * acc_kept, (acc, acc_kept)
    mean_true, var_true, fourth_true = toy_moments()
    for j in range(D + 1):
        assert_moments(res.positions[..., j], mean_true[j], var_true[j], fourth_true[j], n_se=5.0,
                       what=("rebuilt", j))
    resumed = sample(jax.random.key(1), algorithm, x0, **run, resume=ckpts[0])
    np.testing.assert_array_equal(resumed.positions, res.positions)

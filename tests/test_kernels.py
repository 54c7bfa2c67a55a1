"""Gradient kernels in Gibbs with the elastic block (bayesreg.kernels) on a known target."""

import numpy as np
import pytest

import arviz as az
import jax
import jax.numpy as jnp

from bayesreg.kernels import gibbs as gk
from bayesreg.kernels.target import Cache, Target
from bayesreg.sampler import sample_gradient

D = 4
S = np.array([0.5, 1.0, 2.0, 0.2])  # conditional scales of u given eta = 0
A = 1.5  # E[u | eta] = A * eta
M_ETA, SD_ETA = 0.3, 0.15


def toy_target() -> Target:
    """``eta ~ N(0.3, 0.15^2)``, ``u | eta ~ N(A eta, exp(eta)^2 diag S^2)``.

    Written as the posterior is: an unnormalised conditional of ``u`` (the "elastic prior")
    plus a normaliser ``log_norm(eta) = -D eta`` that depends on the "elastic parameter"
    only, and a preconditioner ``u = F w``.  Marginals: ``E u = A M_ETA``,
    ``Var u_j = S_j^2 E exp(2 eta) + A^2 SD_ETA^2``.
    """
    f = jnp.asarray(S)

    def u_of(w):
        return f * w

    def u_lp(w, eta, cache, interior):
        u = u_of(w)
        return -0.5 * jnp.sum(((u - A * eta[0]) / (f * jnp.exp(eta[0]))) ** 2) - 0.5 * ((eta[0] - M_ETA) / SD_ETA) ** 2

    def u_evaluate(w, eta, cache, interior):
        return u_lp(w, eta, cache, interior), interior, jnp.asarray(0), jnp.asarray(True)

    def log_norm(eta):
        return -D * eta[0]

    def evaluate(w, eta, interior, ln):
        lp = u_lp(w, eta, None, interior) + ln
        return lp, lp, interior, jnp.asarray(0), jnp.asarray(True)

    def build_cache(eta, ln):
        return Cache(jnp.zeros((0,)), jnp.asarray(ln, jnp.float64))

    def position(w, eta):
        return jnp.concatenate([u_of(w), eta])

    def coordinates(theta):
        return theta[:D] / f, theta[D:]

    return Target(u_lp, u_evaluate, evaluate, log_norm, build_cache, position, coordinates, 1)


@pytest.mark.parametrize("kind,adapt_mass", [("mala", True), ("hmc", True), ("nuts", True), ("nuts", False)])
def test_gibbs_gradient_kernel_samples_a_known_joint(kind, adapt_mass):
    """Means and variances of u and eta within 5 Monte Carlo standard errors (ESS-based)."""
    rng = np.random.default_rng(0)
    x0 = np.concatenate([rng.normal(size=(4, D)), rng.normal(M_ETA, SD_ETA, size=(4, 1))], axis=1)
    res = sample_gradient(jax.random.key(1), toy_target(), x0, jnp.zeros((1, 3)), kind=kind,
                          step_size=0.3, eta_scale=0.5, num_integration_steps=8, warmup_steps=600,
                          adapt_mass=adapt_mass, elastic_moves=1 if adapt_mass else 3,
                          max_draws=1500, min_draws=1500, chunk_draws=100, thinning=1, progress=False)
    draws = res.positions  # (C, n, D + 1)
    assert res.divergences.mean() < 0.01  # the toy is a mild funnel: rare divergences allowed
    mean_true = np.r_[np.full(D, A * M_ETA), M_ETA]
    e2 = np.exp(2 * M_ETA + 2 * SD_ETA**2)
    var_true = np.r_[S**2 * e2 + A**2 * SD_ETA**2, SD_ETA**2]
    for j in range(D + 1):
        x = draws[..., j]
        ess = float(az.ess(x, method="bulk"))
        assert ess > 50, (kind, j, ess)
        se_mean = np.sqrt(var_true[j] / ess)
        assert abs(x.mean() - mean_true[j]) < 5 * se_mean, (kind, j, x.mean(), mean_true[j])
        # sd of the variance estimate of a near-Gaussian: var * sqrt(2 / ess), heavier tails for u
        assert abs(x.var() - var_true[j]) < 6 * var_true[j] * np.sqrt(3.0 / ess), (kind, j, x.var(), var_true[j])
    acc = res.acceptance.reshape(-1, 2).mean(axis=0)
    assert 0.25 < acc[0] < 0.99 and 0.1 < acc[1] < 0.7, acc  # targets 0.57 (MALA), 0.8; 0.3
    step, inv_mass, eta_scale = res.sigma
    assert step.shape == (4,) and inv_mass.shape == (4, D) and eta_scale.shape == (4, 1, 1)
    if not adapt_mass:
        np.testing.assert_array_equal(inv_mass, 1.0)
    assert np.all(res.grad_evals >= 1)


ETA_COV = np.array([[0.04, 0.0392], [0.0392, 0.04]])  # sd 0.2, correlation 0.98


def correlated_target() -> Target:
    """``eta ~ N(0, ETA_COV)`` (two strongly correlated "elastic parameters", like the overall
    stiffness scale under the exact normaliser), ``u | eta ~ N((eta_0 - eta_1) 1, I)``."""
    prec = jnp.asarray(np.linalg.inv(ETA_COV))

    def u_lp(w, eta, cache, interior):
        return -0.5 * jnp.sum((w - (eta[0] - eta[1])) ** 2) - 0.5 * eta @ prec @ eta

    def evaluate(w, eta, interior, ln):
        lp = u_lp(w, eta, None, interior) + ln
        return lp, lp, interior, jnp.asarray(0), jnp.asarray(True)

    return Target(u_lp, lambda w, eta, c, i: (u_lp(w, eta, c, i), i, jnp.asarray(0), jnp.asarray(True)),
                     evaluate, lambda eta: jnp.zeros(()),
                     lambda eta, ln: Cache(jnp.zeros((0,)), jnp.asarray(ln, jnp.float64)),
                     lambda w, eta: jnp.concatenate([w, eta]), lambda theta: (theta[:2], theta[2:]), 2)


def test_elastic_random_walk_adapts_a_dense_factor_to_correlated_parameters():
    """The warm-up's elastic factor ``L`` follows the parameters' correlation (0.98), and the
    draws recover their covariance within Monte Carlo error."""
    rng = np.random.default_rng(3)
    x0 = np.concatenate([rng.normal(size=(3, 2)), rng.multivariate_normal([0, 0], ETA_COV, size=3)], axis=1)
    res = sample_gradient(jax.random.key(4), correlated_target(), x0, jnp.zeros((1, 3)), kind="hmc",
                          step_size=0.5, eta_scale=0.05, num_integration_steps=4, warmup_steps=1000,
                          elastic_moves=4, max_draws=2000, min_draws=2000, chunk_draws=100, progress=False)
    factor = res.sigma[2]  # (C, 2, 2)
    cov_prop = factor @ np.swapaxes(factor, 1, 2)
    corr = cov_prop[:, 0, 1] / np.sqrt(cov_prop[:, 0, 0] * cov_prop[:, 1, 1])
    assert np.all(corr > 0.9), corr
    eta = res.positions[..., 2:].reshape(-1, 2)
    ess = min(float(az.ess(res.positions[..., j], method="bulk")) for j in (2, 3))
    assert ess > 100, ess
    for j in range(2):
        assert abs(eta[:, j].mean()) < 5 * 0.2 / np.sqrt(ess)
        assert abs(eta[:, j].var() - 0.04) < 5 * 0.04 * np.sqrt(2.0 / ess)
    acc = res.acceptance.reshape(-1, 2).mean(axis=0)
    assert 0.15 < acc[1] < 0.5, acc  # Robbins-Monro toward 0.3 on top of the dense factor


def test_gradient_sampler_resumes_to_the_uninterrupted_draws():
    """Checkpoint after chunk 2 (state leaves and tuned values as a file would hold them),
    resume: the draws equal those of the run never interrupted."""
    rng = np.random.default_rng(2)
    x0 = np.concatenate([rng.normal(size=(2, D)), rng.normal(M_ETA, SD_ETA, size=(2, 1))], axis=1)
    saved = []

    def keep(ckpt, out):
        leaves = jax.tree.leaves(ckpt.states)
        saved.append((ckpt._replace(states=[np.asarray(a) for a in leaves]), out))

    kw = dict(kind="nuts", warmup_steps=40, max_draws=30, min_draws=30, chunk_draws=10, thinning=2,
              progress=False)
    full = sample_gradient(jax.random.key(7), toy_target(), x0, jnp.zeros((1, 3)), on_chunk=keep, **kw)
    ckpt, _ = saved[2]
    draws = tuple(np.concatenate([o[j] for _, o in saved[1:3]], axis=1) for j in range(len(saved[1][1])))
    resumed = sample_gradient(jax.random.key(7), toy_target(), x0, jnp.zeros((1, 3)), resume=ckpt,
                              resume_draws=draws, **kw)
    np.testing.assert_array_equal(resumed.positions, full.positions)
    np.testing.assert_array_equal(resumed.grad_evals, full.grad_evals)


@pytest.mark.parametrize("kind", ["mala", "nuts"])
def test_without_warmup_a_gradient_kernel_samples_at_the_given_step_size(kind):
    """``warmup_steps=0``: the step size given is the one used (before: 1.0 whatever was
    given, the dual averaging's initial average ``exp(0)``)."""
    rng = np.random.default_rng(0)
    x0 = np.concatenate([rng.normal(size=(2, D)), rng.normal(M_ETA, SD_ETA, size=(2, 1))], axis=1)
    for step in (0.05, 0.3):
        res = sample_gradient(jax.random.key(1), toy_target(), x0, jnp.zeros((1, 3)), kind=kind,
                              step_size=step, eta_scale=0.5, warmup_steps=0, max_draws=10,
                              min_draws=10, chunk_draws=10, thinning=1, progress=False)
        np.testing.assert_allclose(res.sigma[0], step)


def test_a_failed_evaluation_at_the_chains_own_parameters_moves_nothing_and_is_counted():
    """The elastic moves compare each proposal with the chain's parameters re-evaluated at
    its new ``u_b``; if that evaluation fails (``-inf``, not ok), no proposal is accepted
    against it (before: any finite proposal was, at a log-ratio of ``+inf``) and the failure
    is counted."""
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
    res = sample_gradient(jax.random.key(2), target._replace(evaluate=evaluate), x0,
                          jnp.zeros((1, 3)), kind="mala", step_size=0.05, eta_scale=0.5,
                          warmup_steps=0, max_draws=10, min_draws=10, chunk_draws=10, thinning=1,
                          progress=False)
    assert np.all(res.positions[..., D] == M_ETA)  # never moved
    assert np.all(res.solve_failures >= 1)  # one per transition at least


def test_warmup_and_sampling_chunks_compile_one_program():
    """Four warm-up chunks and three sampling chunks run one compiled chunk program (the
    sampling is the warm-up's program with the adaptation discarded; BlackJAX's weakly
    typed initial adaptation state would otherwise give the warm-up a second one)."""
    from conftest import compilations

    rng = np.random.default_rng(3)
    x0 = np.concatenate([rng.normal(size=(2, D)), rng.normal(M_ETA, SD_ETA, size=(2, 1))], axis=1)
    with compilations() as compiled:
        sample_gradient(jax.random.key(8), toy_target(), x0, jnp.zeros((1, 3)), kind="nuts",
                        warmup_steps=80, max_draws=30, min_draws=30, chunk_draws=10, thinning=2,
                        progress=False)
    assert compiled.get("jit(mapped)") == 1, compiled


def gaussian_target(dim: int) -> Target:
    """``u ~ N(0, I)``, no elastic parameters (``n_free = 0``)."""

    def u_lp(w, eta, cache, interior):
        return -0.5 * jnp.sum(w**2)

    return Target(u_lp, lambda w, eta, c, i: (u_lp(w, eta, c, i), i, jnp.asarray(0), jnp.asarray(True)),
                     lambda w, eta, i, ln: (u_lp(w, eta, None, i), u_lp(w, eta, None, i), i, jnp.asarray(0),
                                            jnp.asarray(True)),
                     lambda eta: jnp.zeros(()),
                     lambda eta, ln: Cache(jnp.zeros((0,)), jnp.asarray(ln, jnp.float64)),
                     lambda w, eta: w, lambda theta: (theta, jnp.zeros((0,))), 0)


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
    assert np.all(np.abs(xs.mean(axis=0)) < 5 / np.sqrt(ess))
    assert np.all(np.abs(xs.var(axis=0) - 1.0) < 5 * np.sqrt(2.0 / ess))

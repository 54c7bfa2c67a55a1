"""RW-MH driver against a known Gaussian posterior; classic R-hat on known cases."""

from functools import partial

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.linalg as sla

from bayesreg import fem, stiffness
from bayesreg.convergence import gelman_rubin
from bayesreg.posterior import Aux
from bayesreg.sampler import sample
from bayesreg.solver import solve_interior
from conftest import centred_cube


def test_gelman_rubin_known_cases():
    rng = np.random.default_rng(0)
    iid = rng.normal(size=(4, 2000, 3))
    assert np.all(np.abs(gelman_rubin(iid) - 1) < 0.01)
    shifted = iid + np.array([0.0, 0.0, 3.0, 3.0])[:, None, None]
    assert np.all(gelman_rubin(shifted) > 1.5)
    # the formula: W = mean within variance, B/n = variance of means
    x = rng.normal(size=(3, 50))
    n = 50
    w = x.var(1, ddof=1).mean()
    var_plus = (n - 1) / n * w + x.mean(1).var(ddof=1)
    assert gelman_rubin(x) == pytest.approx(np.sqrt(var_plus / w))
    with pytest.raises(ValueError):
        gelman_rubin(np.zeros((1, 10)))


def _quadratic_problem():
    """Boundary displacements of a cube with an elastic prior and a Gaussian stand-in likelihood."""
    mesh = centred_cube()
    lam, mu, t_r = 10.0, 1.0, 50.0
    op, _ = stiffness.build_operator(mesh.nodes, mesh.tets, mesh.boundary)
    grads, vol = fem.shape_gradients(mesh.nodes, mesh.tets)
    perm = np.empty(len(mesh.nodes), int)
    perm[mesh.boundary] = np.arange(len(mesh.boundary))
    perm[mesh.interior] = len(mesh.boundary) + np.arange(len(mesh.interior))
    d = 3 * len(mesh.boundary)
    rng = np.random.default_rng(42)
    q = rng.normal(size=(d, d))
    a_prec = q @ q.T / d * 4.0 + np.eye(d) * 2.0  # likelihood precision (1/mm^2)
    a_mean = rng.normal(size=d)
    lam_e = jnp.full(len(mesh.tets), lam)
    mu_e = jnp.full(len(mesh.tets), mu)

    def logdensity(theta, u_i0):
        u_b = theta.reshape(-1, 3)
        u_i, info = solve_interior(op, lam_e, mu_e, u_b, u_i0, rtol=1e-12)
        u = jnp.concatenate([u_b, u_i])[perm]
        e_r = fem.element_strain_energy(jnp.asarray(grads), jnp.asarray(np.abs(vol)), u[mesh.tets],
                                        lam_e, mu_e)
        r = theta - a_mean
        e_s = 0.5 * r @ (a_prec @ r)
        lp = -e_s - e_r / t_r
        return jnp.where(info.converged, lp, -jnp.inf), Aux(u_i, info, e_s, e_r)

    # exact posterior: precision A + S / T_r, S the Schur complement of K
    k = fem.stiffness_matrix(mesh.nodes, mesh.tets, lam, mu).toarray()
    bd = (3 * mesh.boundary[:, None] + np.arange(3)).ravel()
    idf = (3 * mesh.interior[:, None] + np.arange(3)).ravel()
    s = k[np.ix_(bd, bd)] - k[np.ix_(bd, idf)] @ np.linalg.solve(k[np.ix_(idf, idf)], k[np.ix_(idf, bd)])
    prec = a_prec + s / t_r
    cov = np.linalg.inv(prec)
    mean = cov @ (a_prec @ a_mean)
    return logdensity, mean, cov, len(mesh.interior)


def test_rwmh_reproduces_known_gaussian_posterior():
    logdensity, mean, cov, n_i = _quadratic_problem()
    d = len(mean)
    chol = sla.cholesky(cov, lower=True)
    chains = 4
    x0 = mean + 3.0 * np.random.default_rng(0).normal(size=(chains, d)) @ chol.T
    res = sample(
        jax.random.key(7), logdensity, x0, jnp.zeros((n_i, 3)), 2.38 / np.sqrt(d) * chol,
        thinning=5, warmup_steps=2500, max_draws=3000, min_draws=3000, chunk_draws=500,
        target_acceptance=0.25, progress=False,
    )
    draws = res.positions.reshape(-1, d)
    assert 0.15 < res.acceptance.mean() < 0.4
    assert res.solve_failures.sum() == 0
    import arviz as az

    ess = np.array([float(az.ess(res.positions[:, :, k], method="mean")) for k in range(d)])
    assert ess.min() > 200
    # means within 4.5 Monte Carlo standard errors (joint over d = 24 coordinates)
    z = (draws.mean(0) - mean) / np.sqrt(np.diag(cov) / ess)
    assert np.max(np.abs(z)) < 4.5
    # variances: relative error of a variance estimate ~ sqrt(2 / ESS)
    rel = draws.var(0) / np.diag(cov) - 1
    assert np.max(np.abs(rel) / np.sqrt(2.0 / ess)) < 4.5
    # a cross-covariance too
    c01 = np.cov(draws[:, 0], draws[:, 1])[0, 1]
    assert c01 == pytest.approx(cov[0, 1], abs=4.5 * np.sqrt(cov[0, 0] * cov[1, 1] / ess[:2].min()))
    assert gelman_rubin(res.positions).max() < 1.1


def test_sampler_stops_at_rhat_and_is_reproducible():
    logdensity, mean, cov, n_i = _quadratic_problem()
    d = len(mean)
    chol = sla.cholesky(cov, lower=True)
    x0 = mean + np.random.default_rng(1).normal(size=(3, d)) @ chol.T
    run = partial(sample, jax.random.key(3), logdensity, x0, jnp.zeros((n_i, 3)),
                  2.38 / np.sqrt(d) * chol, thinning=2, warmup_steps=200, max_draws=5000,
                  min_draws=100, chunk_draws=100, rhat_threshold=1.2, progress=False)
    a, b = run(), run()
    assert a.converged and a.positions.shape[1] < 5000
    assert a.rhat_history[-1][1] < 1.2
    np.testing.assert_array_equal(a.positions, b.positions)


def test_sampler_rejects_bad_start():
    logdensity, mean, cov, n_i = _quadratic_problem()

    def bad(theta, u_i0):
        lp, aux = logdensity(theta, u_i0)
        return jnp.where(theta[0] > 100.0, -jnp.inf, lp), aux

    x0 = np.tile(mean, (2, 1))
    x0[:, 0] = 200.0
    with pytest.raises(ValueError, match="zero posterior density"):
        sample(jax.random.key(0), bad, x0, jnp.zeros((n_i, 3)), np.full(len(mean), 0.1),
               progress=False)


def test_sampler_rejects_bad_scales_blocks_and_draw_counts():
    """sigma NaN, 0 or negative, blocks that leave out (or repeat) a coordinate, min_draws >
    max_draws and chunk_draws > max_draws (which returned a whole chunk) were accepted.
    The checks run before anything is traced."""
    from bayesreg.sampler import sample_gradient

    logdensity, mean, cov, n_i = _quadratic_problem()
    d = len(mean)
    x0 = np.tile(mean, (2, 1))
    run = partial(sample, jax.random.key(0), logdensity, x0, jnp.zeros((n_i, 3)), progress=False)
    ok = np.full(d, 0.1)
    for value, match in ((np.nan, "sigma of block 0 must be finite"),
                         (0.0, r"sigma of block 0 \(a vector of scales\) must be > 0, got minimum 0.0"),
                         (-0.1, r"must be > 0, got minimum -0.1")):
        sigma = ok.copy()
        sigma[3] = value
        with pytest.raises(ValueError, match=match):
            run(sigma)
    dense = np.diag(ok)
    dense[1, 0] = np.inf
    with pytest.raises(ValueError, match="sigma of block 0 must be finite"):
        run(dense)
    half = d // 2
    blocks_bad = [
        ((np.arange(half), np.arange(half + 1, d)), rf"blocks must partition range\({d}\) .*missing: \[{half}\]"),
        ((np.arange(half + 1), np.arange(half, d)), rf"repeated: \[{half}\]"),
        ((np.arange(half), np.arange(half, d + 1)), rf"indices outside \[0, {d}\): \[{d}\]"),
        ((np.arange(half), np.arange(half, d) + 0.0), "block 1 must be a 1-D array of integer coordinate indices"),
    ]
    for blocks, match in blocks_bad:
        sig = tuple(np.full(len(b), 0.1) for b in blocks)
        with pytest.raises(ValueError, match=match):
            run(sig, blocks=blocks)
    with pytest.raises(ValueError, match="min_draws must be <= max_draws, got min_draws=100, max_draws=40"):
        run(ok, max_draws=40, min_draws=100, chunk_draws=20)
    with pytest.raises(ValueError, match="chunk_draws must be <= max_draws"):
        run(ok, max_draws=4, min_draws=4, chunk_draws=8)
    # the gradient driver shares the draw checks and checks its own scales (target unused)
    grad = partial(sample_gradient, jax.random.key(0), None, x0, jnp.zeros((n_i, 3)), progress=False)
    with pytest.raises(ValueError, match="chunk_draws must be <= max_draws"):
        grad(max_draws=4, min_draws=4, chunk_draws=8)
    with pytest.raises(ValueError, match="min_draws must be <= max_draws"):
        grad(max_draws=40, min_draws=100, chunk_draws=20)
    for step in (0.0, -1.0, np.nan):
        with pytest.raises(ValueError, match="step_size must be a finite scalar > 0"):
            grad(step_size=step)
    with pytest.raises(ValueError, match="eta_scale must be finite and, as scales, > 0"):
        grad(eta_scale=np.array([0.1, 0.0]))


def test_blocked_kernel_targets_the_same_posterior():
    """Metropolis-within-Gibbs over two blocks leaves the same Gaussian posterior invariant."""
    logdensity, mean, cov, n_i = _quadratic_problem()
    d = len(mean)
    half = d // 2
    blocks = (np.arange(half), np.arange(half, d))
    sig = tuple(2.38 / np.sqrt(len(b)) * sla.cholesky(cov[np.ix_(b, b)], lower=True) for b in blocks)
    x0 = mean + np.random.default_rng(4).normal(size=(4, d)) @ sla.cholesky(cov, lower=True).T
    res = sample(jax.random.key(11), logdensity, x0, jnp.zeros((n_i, 3)), sig, blocks=blocks,
                 thinning=5, warmup_steps=2500, max_draws=3000, min_draws=3000, chunk_draws=500,
                 progress=False)
    assert res.acceptance.shape[-1] == 2
    import arviz as az

    ess = np.array([float(az.ess(res.positions[:, :, k], method="mean")) for k in range(d)])
    draws = res.positions.reshape(-1, d)
    z = (draws.mean(0) - mean) / np.sqrt(np.diag(cov) / ess)
    assert np.max(np.abs(z)) < 4.5
    rel = draws.var(0) / np.diag(cov) - 1
    assert np.max(np.abs(rel) / np.sqrt(2.0 / ess)) < 4.5


def test_split_rhat_detects_a_common_drift():
    rng = np.random.default_rng(5)
    trend = np.linspace(0.0, 5.0, 1000)
    drifting = rng.normal(size=(3, 1000)) + trend  # every chain drifts the same way
    assert gelman_rubin(drifting) < 1.01  # whole-chain R-hat is blind to it
    assert gelman_rubin(drifting, split=True) > 1.2  # the stopping threshold catches it
    assert abs(gelman_rubin(rng.normal(size=(3, 1000)), split=True) - 1) < 0.01


def test_without_warmup_the_given_kernel_samples_unchanged():
    """``warmup_steps=0`` (the paper's fixed kernel): the scale is the one given, no warm-up
    acceptance (NaN, written as null in run.json), and every step is stored."""
    logdensity, mean, cov, n_i = _quadratic_problem()
    d = len(mean)
    sig = 2.38 / np.sqrt(d) * sla.cholesky(cov, lower=True)
    x0 = mean + np.random.default_rng(5).normal(size=(2, d)) @ sig.T
    res = sample(jax.random.key(4), logdensity, x0, jnp.zeros((n_i, 3)), sig, thinning=2,
                 warmup_steps=0, max_draws=40, min_draws=40, chunk_draws=20, progress=False)
    np.testing.assert_array_equal(res.sigma[0], sig)
    assert np.all(np.isnan(res.warmup_acceptance))
    assert res.positions.shape == (2, 40, d) and 0.05 < res.acceptance.mean() < 0.6


def test_split_rhat_monitor_waits_for_enough_draws():
    logdensity, mean, cov, n_i = _quadratic_problem()
    x0 = np.tile(mean, (2, 1)) + 0.01
    res = sample(jax.random.key(2), logdensity, x0, jnp.zeros((n_i, 3)), np.full(len(mean), 0.05),
                 thinning=1, warmup_steps=0, max_draws=6, min_draws=2, chunk_draws=2,
                 rhat_split=True, progress=False)
    assert res.positions.shape[1] >= 4
    assert res.rhat_history[0][1] == np.inf  # 2 draws: no split R-hat yet
    assert np.isfinite(res.rhat_history[-1][1])


def test_resume_from_a_checkpoint_equals_an_uninterrupted_run():
    """Checkpoints after the warm-up and every chunk; continuing from any equals not stopping."""
    from bayesreg.sampler import SamplerCheckpoint

    logdensity, mean, cov, n_i = _quadratic_problem()
    d = len(mean)
    chol = sla.cholesky(cov, lower=True)
    x0 = mean + 2.0 * np.random.default_rng(3).normal(size=(3, d)) @ chol.T
    blocks = (np.arange(d // 2), np.arange(d // 2, d))
    sig = (np.full(d // 2, 0.1), np.full(d - d // 2, 0.1))
    run = partial(sample, jax.random.key(5), logdensity, x0, jnp.zeros((n_i, 3)), sig,
                  blocks=blocks, adapt_diagonal=(True, True), thinning=3, warmup_steps=120,
                  max_draws=60, min_draws=60, chunk_draws=10, progress=False)
    saved = []
    full = run(on_chunk=lambda ckpt, out: saved.append((ckpt, out)))
    assert len(saved) == 1 + 6 and saved[0][1] is None and saved[-1][0].chunks_done == 6
    for cut in (0, 2, 5):  # killed right after the warm-up, after chunk 2, after chunk 5
        ckpt = saved[cut][0]
        assert isinstance(ckpt, SamplerCheckpoint) and ckpt.chunks_done == cut
        draws = None
        if cut:
            draws = tuple(np.concatenate([o[j] for _, o in saved[1:cut + 1]], axis=1) for j in range(len(saved[1][1])))
        resumed = run(resume=ckpt, resume_draws=draws)
        np.testing.assert_array_equal(resumed.positions, full.positions)
        np.testing.assert_array_equal(resumed.interior, full.interior)
        np.testing.assert_array_equal(resumed.acceptance, full.acceptance)
        assert resumed.rhat_history == full.rhat_history

"""The random-walk kernel (bayesreg.sampling.kernels.rwmh): it leaves known posteriors invariant, and
its cached interior map and preconditioner leave the draws where the plain kernel takes them."""

import arviz as az
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.linalg as sla

from bayesreg.sampling import chains
from bayesreg.sampling.convergence import gelman_rubin
from bayesreg.sampling.kernels import rwmh
from bayesreg.model.posterior import condensation, log_density, log_density_condensed, preconditioner
from helpers import box_posterior, quadratic_problem, sample_rwmh


@pytest.fixture(scope="module")
def identified():
    """A box posterior whose elastic parameters are identified (informative Beta priors,
    weak elastic temperature): ``(mesh, post, theta)``, shared by the module's tests."""
    prior = {"lam": (20.0, 20.0, 0.0, 60.0), "mu": (20.0, 20.0, 0.0, 2.0)}
    mesh, post, theta = box_posterior(prior, 30.0, np.array([30.0, 30.0, 30.0, 1.0, 1.0]))
    theta.setflags(write=False)
    return mesh, post, theta


def test_rwmh_reproduces_known_gaussian_posterior():
    logdensity, mean, cov, n_i = quadratic_problem()
    d = len(mean)
    chol = sla.cholesky(cov, lower=True)
    chains = 4
    x0 = mean + 3.0 * np.random.default_rng(0).normal(size=(chains, d)) @ chol.T
    res = sample_rwmh(
        jax.random.key(7), logdensity, x0, jnp.zeros((n_i, 3)), 2.38 / np.sqrt(d) * chol,
        thinning=5, warmup_steps=2500, max_draws=3000, min_draws=3000, chunk_draws=500,
        target_acceptance=0.25, progress=False,
    )
    draws = res.positions.reshape(-1, d)
    assert 0.15 < res.acceptance.mean() < 0.4
    assert res.solve_failures.sum() == 0

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


def test_blocked_kernel_targets_the_same_posterior():
    """Metropolis-within-Gibbs over two blocks leaves the same Gaussian posterior invariant."""
    logdensity, mean, cov, n_i = quadratic_problem()
    d = len(mean)
    half = d // 2
    blocks = (np.arange(half), np.arange(half, d))
    sig = tuple(2.38 / np.sqrt(len(b)) * sla.cholesky(cov[np.ix_(b, b)], lower=True) for b in blocks)
    x0 = mean + np.random.default_rng(4).normal(size=(4, d)) @ sla.cholesky(cov, lower=True).T
    res = sample_rwmh(jax.random.key(11), logdensity, x0, jnp.zeros((n_i, 3)), sig, blocks=blocks,
                 thinning=5, warmup_steps=2500, max_draws=3000, min_draws=3000, chunk_draws=500,
                 progress=False)
    assert res.acceptance.shape[-1] == 2

    ess = np.array([float(az.ess(res.positions[:, :, k], method="mean")) for k in range(d)])
    draws = res.positions.reshape(-1, d)
    z = (draws.mean(0) - mean) / np.sqrt(np.diag(cov) / ess)
    assert np.max(np.abs(z)) < 4.5
    rel = draws.var(0) / np.diag(cov) - 1
    assert np.max(np.abs(rel) / np.sqrt(2.0 / ess)) < 4.5


def test_condensed_chunk_in_pieces_equals_whole_chunks(identified, monkeypatch):
    """The condensed kernel's cache (``H`` at each chain's parameters) passes from piece to
    piece on a CPU with fewer cores than chains (:func:`bayesreg.sampling.chains.chain_pieces`);
    the draws equal those of whole chunks run by vmap, elastic moves accepted included."""
    mesh, post, theta = identified
    nb3 = 3 * len(mesh.boundary)
    ld = lambda th, ui: log_density(post, th, ui, rtol=1e-10)  # noqa: E731
    cond = rwmh.Condensation(lambda th, h: log_density_condensed(post, th, h),
                            lambda th: condensation(post, th), 0, moves=2)
    kernel = rwmh.build_kernel(ld, (np.arange(nb3), np.arange(nb3, post.dim)), cond)
    x0 = np.tile(theta, (3, 1)) + 0.02 * np.random.default_rng(1).normal(size=(3, post.dim))
    states = jax.jit(jax.vmap(lambda x: rwmh.init(x, ld, jnp.zeros((post.op.n_interior, 3)))))(jnp.asarray(x0))
    sig = (jnp.full(nb3, 0.02), jnp.abs(jnp.asarray(theta[nb3:])) * 0.05)
    keys = jax.random.split(jax.random.key(5), 3)
    expect = chains.build_chunk(kernel, 8, 2, 3, method="vectorized").run(keys, states, sig)
    monkeypatch.setattr(chains, "available_cores", lambda: 2)
    assert chains.chain_pieces(3, 8) == 4
    got = chains.build_chunk(kernel, 8, 2, 3, method="pieces").run(keys, states, sig)
    for g, e in zip(jax.tree.leaves(got), jax.tree.leaves(expect)):
        np.testing.assert_allclose(np.asarray(g, float), np.asarray(e, float), rtol=1e-8, atol=1e-10)
    acc = np.asarray(expect[1][3])  # (C, draws, blocks)
    assert acc[..., 1].max() > 0  # elastic moves were accepted (the cache was rebuilt)


@pytest.mark.parametrize("blocked", [pytest.param(False, marks=pytest.mark.heavy), True],
                         ids=["joint", "blocked"])
def test_preconditioned_kernel_gives_the_draws_of_the_block_jacobi_kernel(identified, monkeypatch, blocked):
    """The dense preconditioner (built at every chunk start, carried through the chunk and
    from piece to piece) leaves the chains where block Jacobi takes them: the same proposals,
    the same accept decisions (log-densities equal to the CG tolerance), in fewer CG
    iterations; in pieces on a 2-core CPU as in whole vmapped chunks."""
    mesh, post, theta = identified
    nb3 = 3 * len(mesh.boundary)
    ld = lambda th, ui, pre=None: log_density(post, th, ui, rtol=1e-10, precond=pre)  # noqa: E731
    pre = rwmh.Preconditioner(ld, lambda th: preconditioner(post, th))
    blocks = (np.arange(nb3), np.arange(nb3, post.dim)) if blocked else None
    sig = ((jnp.full(nb3, 0.02), jnp.abs(jnp.asarray(theta[nb3:])) * 0.05) if blocked else
           (jnp.concatenate([jnp.full(nb3, 0.01), jnp.abs(jnp.asarray(theta[nb3:])) * 0.02]),))
    x0 = np.tile(theta, (3, 1)) + 0.02 * np.random.default_rng(1).normal(size=(3, post.dim))
    states = jax.jit(jax.vmap(lambda x: rwmh.init(x, ld, jnp.zeros((post.op.n_interior, 3)))))(jnp.asarray(x0))
    keys = jax.random.split(jax.random.key(6), 3)
    def chunk(kernel, method):
        return chains.build_chunk(kernel, 8, 3, 3, method=method).run(keys, states, sig)

    plain = chunk(rwmh.build_kernel(ld, blocks), "vectorized")
    fast = chunk(rwmh.build_kernel(ld, blocks, preconditioner=pre), "vectorized")
    monkeypatch.setattr(chains, "available_cores", lambda: 2)
    pieces = chunk(rwmh.build_kernel(ld, blocks, preconditioner=pre), "pieces")
    for g, e in zip(jax.tree.leaves(pieces), jax.tree.leaves(fast)):  # the same arithmetic
        np.testing.assert_allclose(np.asarray(g, float), np.asarray(e, float), rtol=1e-12, atol=1e-12)
    (_, out_p), (_, out_f) = plain, fast
    np.testing.assert_array_equal(np.asarray(out_f[0]), np.asarray(out_p[0]))  # positions
    np.testing.assert_allclose(np.asarray(out_f[2]), np.asarray(out_p[2]), rtol=1e-9)  # log p
    np.testing.assert_allclose(np.asarray(out_f[1]), np.asarray(out_p[1]), atol=1e-7)  # interior
    acc = np.asarray(out_p[3])
    assert 0.05 < acc.mean() < 0.95  # some moves accepted, some rejected
    assert np.asarray(out_f[4]).mean() < 0.5 * np.asarray(out_p[4]).mean()  # CG iterations per step
    assert np.asarray(out_f[5]).sum() == 0  # no failed solve


@pytest.mark.slow
def test_condensed_kernel_samples_the_same_posterior(identified):
    """Blocked RW-MH with cached u_b moves (and several per step) against the plain kernel.

    On a posterior whose elastic parameters are identified (informative Beta priors, weak
    elastic temperature), so that both kernels mix within the run and the comparison has
    power; tolerances from the Monte Carlo error (mean ESS of each coordinate).
    """
    mesh, post, theta = identified
    nb3 = 3 * len(mesh.boundary)
    blocks = (np.arange(nb3), np.arange(nb3, post.dim))
    ld = partial_ld = lambda th, ui: log_density(post, th, ui, rtol=1e-10)  # noqa: E731
    rng = np.random.default_rng(3)
    x0 = np.tile(theta, (4, 1))
    x0[:, :nb3] += 0.05 * rng.normal(size=(4, nb3))
    sig = (np.full(nb3, 0.02), np.abs(theta[nb3:]) * 0.05)
    kw = dict(blocks=blocks, adapt_diagonal=(True, True), thinning=4, warmup_steps=2000,
              max_draws=1000, min_draws=1000, chunk_draws=250, progress=False)
    plain = sample_rwmh(jax.random.key(1), partial_ld, x0, jnp.zeros((post.op.n_interior, 3)), sig, **kw)
    cond = rwmh.Condensation(lambda th, h: log_density_condensed(post, th, h),
                        lambda th: condensation(post, th), 0, moves=3)
    fast = sample_rwmh(jax.random.key(2), ld, x0, jnp.zeros((post.op.n_interior, 3)), sig,
                  condensation=cond, **kw)
    assert fast.solve_failures.sum() == 0 and fast.cg_iterations.mean() > 0  # elastic moves solve
    for res in (plain, fast):
        assert 0.1 < res.acceptance.mean() < 0.6
    # means and sds of every coordinate agree within Monte Carlo error (joint, 173 estimands)
    stats = []
    for res in (plain, fast):
        ess = np.array([float(az.ess(res.positions[:, :, k], method="mean")) for k in range(post.dim)])
        d = res.positions.reshape(-1, post.dim)
        stats.append((d.mean(0), d.std(0), np.maximum(ess, 10)))
    (m1, s1, e1), (m2, s2, e2) = stats
    z = (m1 - m2) / np.sqrt(s1**2 / e1 + s2**2 / e2)
    assert np.max(np.abs(z)) < 5.0
    rel = np.log(s2 / s1) / np.sqrt(1 / (2 * e1) + 1 / (2 * e2))  # sd of log(sd) ~ 1/sqrt(2 ESS)
    assert np.max(np.abs(rel)) < 5.0

"""The driver (bayesreg.sampling.driver): stopping, argument checks, runs without warm-up, resuming
from a checkpoint, one compiled program, and the record of how a run was sampled."""

from functools import partial

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.linalg as sla

from bayesreg.sampling.chains import CHAIN_METHODS
from bayesreg.sampling.kernels.rwmh import Condensation, Preconditioner
from bayesreg.model.posterior import Aux
from bayesreg.sampling.driver import SamplerCheckpoint, WarmupCheckpoint
from bayesreg.fem.solver import SolveInfo
from conftest import compilations
from helpers import (
    D, gaussian_target, M_ETA, quadratic_problem, sample_gibbs, sample_rwmh, SD_ETA,
    toy_target)


def test_sampler_stops_at_the_papers_rhat_and_is_reproducible():
    logdensity, mean, cov, n_i = quadratic_problem()
    d = len(mean)
    chol = sla.cholesky(cov, lower=True)
    x0 = mean + np.random.default_rng(1).normal(size=(3, d)) @ chol.T
    run = partial(sample_rwmh, jax.random.key(3), logdensity, x0, jnp.zeros((n_i, 3)),
                  2.38 / np.sqrt(d) * chol, thinning=2, warmup_steps=200, max_draws=5000,
                  min_draws=100, chunk_draws=100, stop="paper", rhat_threshold=1.2, progress=False)
    a, b = run(), run()
    assert a.converged and a.positions.shape[1] < 5000
    assert a.rhat_history[-1][1] < 1.2 and np.isnan(a.rhat_history[-1][2])  # no rank figures
    assert a.info.stop_rule.kind == "paper"
    np.testing.assert_array_equal(a.positions, b.positions)


def test_sampler_stops_at_the_first_chunk_meeting_the_rank_rule_as_arviz_measures_it():
    """The default rule: after ``min_draws``, stop at the first chunk where every estimand's
    rank-normalised R-hat is <= 1.01 and bulk and tail ESS >= 400, figures that ArviZ's
    ``az.summary`` of the final draws confirms (monitored estimands: the coordinates and
    the exponential of the first, a positive quantity on its natural scale)."""
    import arviz as az

    from bayesreg.sampling.diagnostics import to_datatree

    def logdensity(x, interior):  # a 2-D standard normal
        solve = SolveInfo(jnp.asarray(0), jnp.asarray(0.0), jnp.asarray(True))
        return -0.5 * jnp.sum(x ** 2), Aux(interior, solve, jnp.zeros(()), jnp.zeros(()))

    def estimands(draws):
        return np.concatenate([draws, np.exp(draws[..., :1])], axis=-1)

    x0 = 2.0 * np.random.default_rng(1).normal(size=(3, 2))
    res = sample_rwmh(jax.random.key(3), logdensity, x0, jnp.zeros((0, 3)), np.full(2, 1.7),
                 thinning=2, warmup_steps=200, max_draws=5000, min_draws=100, chunk_draws=100,
                 estimands=estimands, progress=False)
    assert res.info.stop_rule.kind == "rank" and res.converged
    hist = np.array(res.rhat_history)
    n = res.positions.shape[1]
    assert hist[-1, 0] == n < 5000
    met = (hist[:, 2] <= 1.01) & (hist[:, 3] >= 400) & (hist[:, 4] >= 400)
    assert met[-1] and not met[:-1].any()  # the first chunk that meets it, and no later
    assert np.all(np.isnan(hist[hist[:, 0] < 100, 2]))  # not checked before min_draws
    tree = to_datatree({"x": estimands(res.positions)})
    summary = az.summary(tree, ci_prob=0.9)
    assert summary["r_hat"].max() == pytest.approx(hist[-1, 2], rel=1e-9)
    assert summary["ess_bulk"].min() == pytest.approx(hist[-1, 3], rel=1e-6)
    tail = az.ess(tree, method="tail", prob=(0.05, 0.95))["x"].values  # the 5% and 95% quantiles
    assert tail.min() == pytest.approx(hist[-1, 4], rel=1e-6)


def test_the_paper_and_rank_rules_are_checked_and_unknown_rules_refused():
    logdensity, mean, cov, n_i = quadratic_problem()
    x0 = np.tile(mean, (2, 1)) + 0.01
    for bad, match in (({"stop": "classic"}, "stop rule must be one of"),
                       ({"rhat_rank_max": 1.0}, "R-hat thresholds must be > 1"),
                       ({"ess_min": 0.0}, "ess_min must be > 0")):
        with pytest.raises(ValueError, match=match):
            sample_rwmh(jax.random.key(0), logdensity, x0, jnp.zeros((n_i, 3)), np.full(len(mean), 0.05),
                   thinning=1, warmup_steps=0, max_draws=4, min_draws=4, chunk_draws=2,
                   progress=False, **bad)


def test_sampler_rejects_bad_start():
    logdensity, mean, cov, n_i = quadratic_problem()

    def bad(theta, u_i0):
        lp, aux = logdensity(theta, u_i0)
        return jnp.where(theta[0] > 100.0, -jnp.inf, lp), aux

    x0 = np.tile(mean, (2, 1))
    x0[:, 0] = 200.0
    with pytest.raises(ValueError, match="zero posterior density"):
        sample_rwmh(jax.random.key(0), bad, x0, jnp.zeros((n_i, 3)), np.full(len(mean), 0.1),
               progress=False)


def test_sampler_rejects_bad_scales_blocks_and_draw_counts():
    """Refused with the argument named, before anything is traced: a sigma NaN, 0 or
    negative, blocks that leave out (or repeat) a coordinate or are not integer indices,
    min_draws > max_draws and chunk_draws > max_draws; the gradient kernel also checks its
    step size and elastic scales."""
    logdensity, mean, cov, n_i = quadratic_problem()
    d = len(mean)
    x0 = np.tile(mean, (2, 1))
    run = partial(sample_rwmh, jax.random.key(0), logdensity, x0, jnp.zeros((n_i, 3)), progress=False)
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
    # the driver's draw checks hold for every kernel; the gradient kernel checks its own scales
    grad = partial(sample_gibbs, jax.random.key(0), toy_target(), x0, jnp.zeros((n_i, 3)), progress=False)
    with pytest.raises(ValueError, match="chunk_draws must be <= max_draws"):
        grad(max_draws=4, min_draws=4, chunk_draws=8)
    with pytest.raises(ValueError, match="min_draws must be <= max_draws"):
        grad(max_draws=40, min_draws=100, chunk_draws=20)
    for step in (0.0, -1.0, np.nan):
        with pytest.raises(ValueError, match="step_size must be a finite scalar > 0"):
            grad(step_size=step)
    with pytest.raises(ValueError, match="eta_scale must be finite and, as scales, > 0"):
        grad(eta_scale=np.array([0.1, 0.0]))


def test_without_warmup_the_given_kernel_samples_unchanged():
    """``warmup_steps=0`` (the paper's fixed kernel): the scale is the one given, no warm-up
    acceptance (NaN, written as null in run.json), and every step is stored."""
    logdensity, mean, cov, n_i = quadratic_problem()
    d = len(mean)
    sig = 2.38 / np.sqrt(d) * sla.cholesky(cov, lower=True)
    x0 = mean + np.random.default_rng(5).normal(size=(2, d)) @ sig.T
    res = sample_rwmh(jax.random.key(4), logdensity, x0, jnp.zeros((n_i, 3)), sig, thinning=2,
                 warmup_steps=0, max_draws=40, min_draws=40, chunk_draws=20, progress=False)
    np.testing.assert_array_equal(res.sigma[0], sig)
    assert np.all(np.isnan(res.warmup_acceptance))
    assert res.positions.shape == (2, 40, d) and 0.05 < res.acceptance.mean() < 0.6
    assert res.info.warmup_steps == 0 and res.info.thinning == 2
    assert res.info.preconditioner == "unknown"  # neither a Preconditioner nor a name given


def test_split_rhat_monitor_waits_for_enough_draws():
    logdensity, mean, cov, n_i = quadratic_problem()
    x0 = np.tile(mean, (2, 1)) + 0.01
    res = sample_rwmh(jax.random.key(2), logdensity, x0, jnp.zeros((n_i, 3)), np.full(len(mean), 0.05),
                 thinning=1, warmup_steps=0, max_draws=6, min_draws=2, chunk_draws=2,
                 rhat_split=True, progress=False)
    assert res.positions.shape[1] >= 4
    assert res.rhat_history[0][1] == np.inf  # 2 draws: no split R-hat yet
    assert np.isfinite(res.rhat_history[-1][1])


def test_resume_from_a_checkpoint_equals_an_uninterrupted_run():
    """Checkpoints after every warm-up chunk, the warm-up and every chunk; continuing from
    any equals not stopping."""
    logdensity, mean, cov, n_i = quadratic_problem()
    d = len(mean)
    chol = sla.cholesky(cov, lower=True)
    x0 = mean + 2.0 * np.random.default_rng(3).normal(size=(3, d)) @ chol.T
    blocks = (np.arange(d // 2), np.arange(d // 2, d))
    sig = (np.full(d // 2, 0.1), np.full(d - d // 2, 0.1))
    run = partial(sample_rwmh, jax.random.key(5), logdensity, x0, jnp.zeros((n_i, 3)), sig,
                  blocks=blocks, adapt_diagonal=(True, True), thinning=3, warmup_steps=120,
                  max_draws=60, min_draws=60, chunk_draws=10, progress=False)
    saved, warm = [], []
    full = run(on_chunk=lambda ckpt, out: saved.append((ckpt, out)), on_warmup_chunk=warm.append)
    assert len(saved) == 1 + 6 and saved[0][1] is None and saved[-1][0].chunks_done == 6
    # the warm-up (4 chunks, its windows ending after chunks 2 and 3) cut after any chunk
    assert [w.chunks_done for w in warm] == [1, 2, 3]
    for w in warm:
        assert isinstance(w, WarmupCheckpoint)
        resumed = run(resume=w)
        np.testing.assert_array_equal(resumed.positions, full.positions)
        assert resumed.info == full.info
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
        assert resumed.info == full.info  # the same record, adapted scales included
    assert full.info.blocks == ("block0", "block1") and full.info.solves_per_step == 2.0
    assert full.info.warmup_steps == 120 and len(full.info.adapted["proposal_sd_rms_per_block"]) == 2


@pytest.mark.parametrize("kind", ["mala", "nuts"])
def test_without_warmup_a_gradient_kernel_samples_at_the_given_step_size(kind):
    """``warmup_steps=0``: the step size given is the one used (not the dual averaging's
    initial average ``exp(0) = 1``)."""
    rng = np.random.default_rng(0)
    x0 = np.concatenate([rng.normal(size=(2, D)), rng.normal(M_ETA, SD_ETA, size=(2, 1))], axis=1)
    for step in (0.05, 0.3):
        res = sample_gibbs(jax.random.key(1), toy_target(), x0, jnp.zeros((1, 3)), kind=kind,
                              step_size=step, eta_scale=0.5, warmup_steps=0, max_draws=10,
                              min_draws=10, chunk_draws=10, thinning=1, progress=False)
        np.testing.assert_allclose(res.sigma[0], step)


def test_gradient_sampler_resumes_to_the_uninterrupted_draws():
    """Checkpoint in the warm-up and after chunk 2 (state leaves and tuned values as a file
    would hold them), resume: the draws equal those of the run never interrupted."""
    rng = np.random.default_rng(2)
    x0 = np.concatenate([rng.normal(size=(2, D)), rng.normal(M_ETA, SD_ETA, size=(2, 1))], axis=1)
    saved = []

    def keep(ckpt, out):
        leaves = jax.tree.leaves(ckpt.states)
        saved.append((ckpt._replace(states=[np.asarray(a) for a in leaves]), out))

    kw = dict(kind="nuts", warmup_steps=40, max_draws=30, min_draws=30, chunk_draws=10, thinning=2,
              progress=False)
    warm = []
    full = sample_gibbs(jax.random.key(7), toy_target(), x0, jnp.zeros((1, 3)), on_chunk=keep,
                        on_warmup_chunk=warm.append, **kw)
    assert [w.chunks_done for w in warm] == [1]  # cut in the warm-up: the adaptation's state kept
    from_warmup = sample_gibbs(jax.random.key(7), toy_target(), x0, jnp.zeros((1, 3)), resume=warm[0], **kw)
    np.testing.assert_array_equal(from_warmup.positions, full.positions)
    np.testing.assert_array_equal(from_warmup.sigma[0], full.sigma[0])
    ckpt, _ = saved[2]
    draws = tuple(np.concatenate([o[j] for _, o in saved[1:3]], axis=1) for j in range(len(saved[1][1])))
    resumed = sample_gibbs(jax.random.key(7), toy_target(), x0, jnp.zeros((1, 3)), resume=ckpt,
                              resume_draws=draws, **kw)
    np.testing.assert_array_equal(resumed.positions, full.positions)
    np.testing.assert_array_equal(resumed.grad_evals, full.grad_evals)


def test_warmup_and_sampling_chunks_compile_one_program():
    """Four warm-up chunks and three sampling chunks run one compiled chunk program (the
    sampling is the warm-up's program with the adaptation discarded; BlackJAX's weakly
    typed initial adaptation state would otherwise give the warm-up a second one)."""
    rng = np.random.default_rng(3)
    x0 = np.concatenate([rng.normal(size=(2, D)), rng.normal(M_ETA, SD_ETA, size=(2, 1))], axis=1)
    with compilations() as compiled:
        sample_gibbs(jax.random.key(8), toy_target(), x0, jnp.zeros((1, 3)), kind="nuts",
                        warmup_steps=80, max_draws=30, min_draws=30, chunk_draws=10, thinning=2,
                        progress=False)
    assert compiled.get("jit(mapped)") == 1, compiled


def _standard_normal(x, interior):
    """``log N(x; 0, I)`` with the by-products of a log-density (placeholder solve figures)."""
    solve = SolveInfo(jnp.asarray(0), jnp.asarray(0.0), jnp.asarray(True))
    return -0.5 * jnp.sum(x**2), Aux(interior, solve, jnp.zeros(()), jnp.zeros(()))


def test_sample_records_how_the_random_walk_ran():
    """``SamplerResult.info`` of :func:`sample`: kind ``"rwmh"``; the blocks' names
    (``("joint",)`` for one block, or the names given); one solve per block and step, one
    fewer with a condensation (its block's moves solve nothing); the preconditioner
    (``"dense"`` with a :class:`Preconditioner`, else the ``cg_preconditioner`` named); the
    chain method in use; the thinning; the warm-up in whole chunks; the adapted proposal
    scales.  (Default block names and ``"unknown"`` without a preconditioner: the resume
    and no-warm-up tests above.)"""
    x0 = 0.1 * np.arange(8.0).reshape(2, 4)
    zero = jnp.zeros((0, 3))
    run = partial(sample_rwmh, jax.random.key(0), _standard_normal, x0, zero, thinning=3, max_draws=4,
                  min_draws=4, chunk_draws=2, progress=False)
    info = run(np.ones(4), warmup_steps=7, chain_method="vectorized", cg_preconditioner="spectral").info
    assert info.kind == "rwmh" and info.blocks == ("joint",) and info.solves_per_step == 1.0
    assert info.preconditioner == "spectral" and not info.condensed
    assert info.chain_method == "vectorized" and info.thinning == 3
    assert info.warmup_steps == 12  # 7 steps asked: two chunks of 2 draws x 3 steps
    assert info.rhat_threshold == 1.2 and not info.rhat_split
    assert len(info.adapted["proposal_sd_rms_per_block"]) == 1 and info.adapted["elastic_proposal_sd"] is None

    blocks = (np.arange(2), np.arange(2, 4))
    condensed = Condensation(lambda x, h: _standard_normal(x, zero), lambda x: jnp.zeros(()), 0, moves=2)
    pre = Preconditioner(lambda x, guess, p: _standard_normal(x, guess), lambda x: jnp.zeros(()))
    info = run((np.ones(2), np.ones(2)), blocks=blocks, block_names=("u_b", "elastic"), warmup_steps=0,
               condensation=condensed, preconditioner=pre, cg_preconditioner="block-jacobi").info
    assert info.blocks == ("u_b", "elastic") and info.solves_per_step == 1.0 and info.condensed
    assert info.preconditioner == "dense"  # the Preconditioner given, whatever cg_preconditioner says
    assert info.chain_method in CHAIN_METHODS and info.chain_method != "auto"
    np.testing.assert_allclose(info.adapted["elastic_proposal_sd"], [1.0, 1.0])  # as given: no warm-up
    with pytest.raises(ValueError, match="2 blocks but 1 block_names"):
        run((np.ones(2), np.ones(2)), blocks=blocks, block_names=("u_b",), warmup_steps=0)


def test_sample_gradient_records_how_the_gradient_kernel_ran():
    """``SamplerResult.info`` of :func:`sample_gradient`: the kernel; the blocks (``u_b`` and
    ``elastic``, or ``u_b`` alone without free parameters); the target's preconditioner and
    condensed flag; the solves counted per step, ``elastic_moves + 1`` for a condensed
    target with free parameters (the trajectories solve nothing) and ``None`` otherwise
    (every gradient solves, a varying number per step); the warm-up in whole chunks; the
    adapted step sizes."""
    rng = np.random.default_rng(0)
    x0 = np.concatenate([rng.normal(size=(2, D)), rng.normal(M_ETA, SD_ETA, size=(2, 1))], axis=1)
    # the chunk program of the MALA run without warm-up above (compiled once for both)
    kw = dict(kind="mala", elastic_moves=1, thinning=1, max_draws=10, min_draws=10, chunk_draws=10,
              progress=False)
    info = sample_gibbs(jax.random.key(1), toy_target(), x0, jnp.zeros((1, 3)), warmup_steps=15, **kw).info
    assert info.kind == "mala" and info.blocks == ("u_b", "elastic")
    assert info.solves_per_step is None and info.preconditioner == "block-jacobi" and not info.condensed
    assert info.warmup_steps == 20 and info.thinning == 1  # 15 steps asked: two chunks of 10
    assert info.chain_method in CHAIN_METHODS and info.chain_method != "auto"
    assert len(info.adapted["step_size_per_chain"]) == 2

    condensed = toy_target()._replace(condensed=True, preconditioner="dense")
    info = sample_gibbs(jax.random.key(1), condensed, x0, jnp.zeros((1, 3)), warmup_steps=0,
                           **{**kw, "elastic_moves": 3}).info
    assert info.solves_per_step == 4.0 and info.preconditioner == "dense" and info.condensed
    assert info.warmup_steps == 0

    no_free = gaussian_target(3)._replace(condensed=True, preconditioner="spectral")
    info = sample_gibbs(jax.random.key(1), no_free, x0[:, :3], jnp.zeros((1, 3)), warmup_steps=0, **kw).info
    assert info.blocks == ("u_b",) and info.solves_per_step is None and info.preconditioner == "spectral"

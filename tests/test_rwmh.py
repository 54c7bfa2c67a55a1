"""The random-walk kernel (bayesreg.kernels.rwmh): its cached interior map and preconditioner
leave the draws where the plain kernel takes them."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from bayesreg import chains
from bayesreg.kernels import rwmh
from bayesreg.posterior import log_density
from test_posterior import _box_posterior


def test_condensed_chunk_in_pieces_equals_whole_chunks(monkeypatch):
    """The condensed kernel's cache (``H`` at each chain's parameters) passes from piece to
    piece on a CPU with fewer cores than chains (:func:`bayesreg.chains.chain_pieces`);
    the draws equal those of whole chunks run by vmap, elastic moves accepted included."""
    from bayesreg.posterior import condensation, log_density_condensed

    prior = {"lam": (20.0, 20.0, 0.0, 60.0), "mu": (20.0, 20.0, 0.0, 2.0)}
    mesh, post, theta = _box_posterior(prior, 30.0, np.array([30.0, 30.0, 30.0, 1.0, 1.0]))
    nb3 = 3 * len(mesh.boundary)
    ld = lambda th, ui: log_density(post, th, ui, rtol=1e-10)  # noqa: E731
    cond = rwmh.Condensation(lambda th, h: log_density_condensed(post, th, h),
                            lambda th: condensation(post, th), 0, moves=2)
    kernel = rwmh.build_kernel(ld, (np.arange(nb3), np.arange(nb3, post.dim)), cond)
    x0 = np.tile(theta, (3, 1)) + 0.02 * np.random.default_rng(1).normal(size=(3, post.dim))
    states = jax.vmap(lambda x: rwmh.init(x, ld, jnp.zeros((post.op.n_interior, 3))))(jnp.asarray(x0))
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


@pytest.mark.parametrize("blocked", [False, True], ids=["joint", "blocked"])
def test_preconditioned_kernel_gives_the_draws_of_the_block_jacobi_kernel(monkeypatch, blocked):
    """The dense preconditioner (built at every chunk start, carried through the chunk and
    from piece to piece) leaves the chains where block Jacobi takes them: the same proposals,
    the same accept decisions (log-densities equal to the CG tolerance), in fewer CG
    iterations; in pieces on a 2-core CPU as in whole vmapped chunks."""
    from bayesreg.posterior import preconditioner

    prior = {"lam": (20.0, 20.0, 0.0, 60.0), "mu": (20.0, 20.0, 0.0, 2.0)}
    mesh, post, theta = _box_posterior(prior, 30.0, np.array([30.0, 30.0, 30.0, 1.0, 1.0]))
    nb3 = 3 * len(mesh.boundary)
    ld = lambda th, ui, pre=None: log_density(post, th, ui, rtol=1e-10, precond=pre)  # noqa: E731
    pre = rwmh.Preconditioner(ld, lambda th: preconditioner(post, th))
    blocks = (np.arange(nb3), np.arange(nb3, post.dim)) if blocked else None
    sig = ((jnp.full(nb3, 0.02), jnp.abs(jnp.asarray(theta[nb3:])) * 0.05) if blocked else
           (jnp.concatenate([jnp.full(nb3, 0.01), jnp.abs(jnp.asarray(theta[nb3:])) * 0.02]),))
    x0 = np.tile(theta, (3, 1)) + 0.02 * np.random.default_rng(1).normal(size=(3, post.dim))
    states = jax.vmap(lambda x: rwmh.init(x, ld, jnp.zeros((post.op.n_interior, 3))))(jnp.asarray(x0))
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


"""The chain scheduler (bayesreg.sampling.chains): every method gives the draws of every other."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from bayesreg.sampling import chains
from bayesreg.sampling.kernels import rwmh
from helpers import quadratic_problem


@pytest.mark.parametrize("per_chain", [False, True])
def test_chains_in_host_threads_equal_vmapped_chains(monkeypatch, per_chain):
    # equal groups, at least one thread per core
    assert [chains.chain_threads(c, 2) for c in (1, 2, 3, 4, 5, 6)] == [1, 2, 3, 2, 5, 2]
    assert [chains.chain_threads(c, 16) for c in (3, 64, 1024)] == [3, 16, 16]
    with pytest.raises(ValueError, match="n_chains"):
        chains.chain_threads(0, 2)

    def one_chain(key, x, scale):  # a random walk to a sphere: a while_loop of chain-dependent length
        def body(c):
            x_, k, n = c
            k, sub = jax.random.split(k)
            return x_ + scale * jax.random.normal(sub, x_.shape), k, n + 1

        x, _, n = jax.lax.while_loop(lambda c: (jnp.sum(c[0] ** 2) < 16.0) & (c[2] < 5000), body, (x, key, 0))
        return x, n

    keys = jax.random.split(jax.random.key(7), 4)
    x0 = jnp.asarray(np.random.default_rng(0).normal(size=(4, 3)))
    scale = jnp.asarray([0.1, 0.2, 0.3, 0.4]) if per_chain else jnp.asarray(0.25)
    expect = jax.vmap(one_chain, in_axes=(0, 0, 0 if per_chain else None))(keys, x0, scale)
    monkeypatch.setattr(chains, "chain_threads", lambda n: 2)  # 2 threads of 2 chains, on any machine
    mapped = chains.map_chains(one_chain, 4, per_chain, method="threads")
    assert mapped.method == "threads"
    run = mapped.run
    for _ in range(2):  # the first call compiles group 0 alone, the second runs both in the pool
        got = run(keys, x0, scale)
        np.testing.assert_allclose(got[0], expect[0], rtol=1e-12)
        np.testing.assert_array_equal(got[1], expect[1])
    assert len(set(np.asarray(expect[1]).tolist())) > 1  # the chains' loops did differ in length


@pytest.mark.parametrize("method", ["threads", "pieces"])
def test_ctrl_c_while_chains_run_in_threads_is_raised_at_once(monkeypatch, request, method):
    """Ctrl-C while the chains' chunk runs in worker threads reaches the caller at once, not
    after the running tasks (at a large mesh a chunk runs for minutes)."""
    import signal
    import threading
    import time

    monkeypatch.setattr(chains, "chain_threads", lambda n: 2)
    monkeypatch.setattr(chains, "available_cores", lambda: 2)

    # tasks of 1 s: 2 chains in 2 threads of one chain each, or 3 chains cut into 2 pieces
    # each on 2 workers
    n_chains, n_draws, pause = (2, 2, 1.0) if method == "threads" else (3, 2, 1.0)

    def slow(x):
        time.sleep(pause)
        return x

    def piece(draw_keys, carry, params):
        y = jax.pure_callback(slow, jax.ShapeDtypeStruct(carry.shape, carry.dtype), carry)
        return y, jnp.zeros(draw_keys.shape[:1])

    def one_chain(key, state, params):
        return piece(jax.random.split(key, n_draws), state, params)

    mapped = chains.map_chains(one_chain, n_chains, False, method=method, piece=piece,
                               n_draws=n_draws)
    assert mapped.method == method
    keys, states = jax.random.split(jax.random.key(0), n_chains), jnp.zeros((n_chains, 3))
    mapped.run(keys, states, None)  # the first call compiles (its first task in this thread)
    main = threading.main_thread().ident
    # Python's Ctrl-C handler, whatever the launcher left: a job started in the background by
    # a non-interactive shell inherits SIGINT ignored, and Python then installs none
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    request.addfinalizer(lambda: signal.signal(signal.SIGINT, previous))
    timer = threading.Timer(0.3, signal.pthread_kill, (main, signal.SIGINT))
    t0 = time.monotonic()
    timer.start()
    with pytest.raises(KeyboardInterrupt):
        mapped.run(keys, states, None)
    assert time.monotonic() - t0 < 0.9  # before the running tasks ended (at 1 s)
    time.sleep(pause)  # the abandoned tasks end on their own


def test_chunk_pieces_on_a_cpu_equal_whole_chunks(monkeypatch):
    """3 chains on 2 cores: a chunk of 6 draws runs as 2 pieces per chain on 2 workers, and gives
    the draws of the whole chunks run by vmap (per-chain states and warm starts)."""
    assert [chains.chain_pieces(c, 100, 2) for c in (1, 2, 3, 4, 5)] == [1, 1, 4, 1, 4]
    assert [chains.chain_pieces(c, 100, 4) for c in (3, 6, 10, 8)] == [1, 4, 4, 1]
    assert chains.chain_pieces(3, 50, 2) == 2  # 2 P pieces where the chunk allows, else P
    assert chains.chain_pieces(3, 25, 2) == 1  # an odd chunk is not cut: whole chains in 3 threads
    assert chains.chain_pieces(3, None, 2) == 1

    logdensity, mean, cov, n_i = quadratic_problem()
    kernel = rwmh.build_kernel(logdensity)
    x0 = mean + 0.1 * np.random.default_rng(5).normal(size=(3, len(mean)))
    states = jax.jit(jax.vmap(lambda x: rwmh.init(x, logdensity, jnp.zeros((n_i, 3)))))(jnp.asarray(x0))
    sig = (jnp.full(len(mean), 0.05),)
    keys = jax.random.split(jax.random.key(3), 3)
    expect = chains.build_chunk(kernel, 6, 3, 3, method="vectorized").run(keys, states, sig)
    monkeypatch.setattr(chains, "available_cores", lambda: 2)
    chunk = chains.build_chunk(kernel, 6, 3, 3, method="pieces")
    assert chunk.method == "pieces"
    for _ in range(2):  # the first call compiles chain 0's first piece alone
        got = chunk.run(keys, states, sig)
        for g, e in zip(jax.tree.leaves(got), jax.tree.leaves(expect)):
            assert g.shape == e.shape
            np.testing.assert_allclose(np.asarray(g, float), np.asarray(e, float), rtol=1e-9, atol=1e-12)
    acc = np.asarray(expect[1][3])
    assert 0 < acc.mean() < 1  # some proposals were rejected, some accepted


def test_methods_resolve_as_documented(monkeypatch):
    """``auto`` is vectorized on an accelerator; on a CPU pieces where the chains do not
    split evenly over the cores, else threads, else one sequential map; pieces is refused
    for a chunk that cannot be cut; an unknown method is refused."""
    monkeypatch.setattr(chains, "available_cores", lambda: 2)
    assert chains.resolve_method("auto", 3, 50, can_piece=True) == "pieces"
    assert chains.resolve_method("auto", 3, 50, can_piece=False) == "threads"
    assert chains.resolve_method("auto", 4, 50, can_piece=True) == "threads"
    assert chains.resolve_method("auto", 3, 25, can_piece=True) == "threads"  # an odd chunk
    monkeypatch.setattr(chains, "available_cores", lambda: 1)
    assert chains.resolve_method("auto", 3, 50, can_piece=True) == "sequential"
    assert chains.resolve_method("vectorized", 3, 50) == "vectorized"
    monkeypatch.setattr(jax, "default_backend", lambda: "gpu")
    assert chains.resolve_method("auto", 3, 50, can_piece=True) == "vectorized"
    with pytest.raises(ValueError, match="pieces.* cannot be cut|can be cut into pieces"):
        chains.resolve_method("pieces", 3, 50, can_piece=False)
    with pytest.raises(ValueError, match="unknown chain method 'parallel'"):
        chains.resolve_method("parallel", 3, 50)

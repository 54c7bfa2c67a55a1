"""Timings of the three hot paths on a small mesh, with pytest-benchmark.

Not part of the test suite (whose ``testpaths`` are ``tests/`` and ``bayesreg/``); run it from
the repository root, in one process (pytest-benchmark does not time under xdist)::

    pytest benchmarks/test_benchmarks.py -n 0 --benchmark-only
    pytest benchmarks/test_benchmarks.py -n 0 --benchmark-only --benchmark-autosave \
        --benchmark-storage=benchmarks/results                  # keep a run (git-ignored)
    pytest benchmarks/test_benchmarks.py -n 0 --benchmark-only --benchmark-compare \
        --benchmark-storage=benchmarks/results                  # compare with the last kept

The problem is ``benchmarks/run.py --quick``'s: the MNI152 brain on 3 mm images with a 26 mm
mesh (about 280 nodes), cached in ``benchmarks/.cache/`` so that later runs time the same
mesh.  Each benchmark calls one jitted function on fixed inputs (compiled before timing),
so every round repeats the same arithmetic:

* ``test_logdensity``: the paper model's log-density (:func:`bayesreg.inference.targets.make_logdensity`)
  at a chain's start, the interior CG solve warm-started from a nearby position's solution;
* ``test_rwmh_step``: one step of the paper's joint random walk
  (:func:`bayesreg.sampling.kernels.rwmh.build_kernel`, with the sampler's CG preconditioner);
* ``test_nuts_transition``: one transition of the default kernel
  (:func:`bayesreg.sampling.kernels.gibbs.build_kernel`: a NUTS trajectory on ``u_b``, then the
  configured elastic random-walk moves) on the quickstart model, at the config's initial
  step size (its trajectory length is in the benchmark's ``extra_info``).
"""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

import bayesreg

bayesreg.configure_jax()  # float64, XLA flags, BLAS threads: before any JAX computation

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

from bayesreg.inference.initialisation import initialise  # noqa: E402
from bayesreg.sampling.kernels import gibbs, rwmh  # noqa: E402
from bayesreg.model.problem import assemble  # noqa: E402
from bayesreg.inference.targets import (  # noqa: E402
    dense_preconditioning, gradient_target, make_logdensity, rw_preconditioner)

sys.path.insert(0, str(Path(__file__).resolve().parent))
import run  # noqa: E402  (benchmarks/run.py: the cached problem)

EDGE_MM, RESOLUTION_MM = 26.0, 3.0


@pytest.fixture(scope="module")
def data():
    return run.problem_data(EDGE_MM, RESOLUTION_MM, run.REPO / "benchmarks" / ".cache")[0]


def _setup(data, kernel: str, extra=()):
    cfg = run.with_chains(run.kernel_config(kernel, EDGE_MM, RESOLUTION_MM, extra), 2)
    problem = assemble(cfg, data)
    return problem, cfg, initialise(problem, cfg)


@pytest.fixture(scope="module")
def paper(data):
    """The paper model and its starts."""
    return _setup(data, "rwmh")


def test_logdensity(benchmark, paper):
    problem, cfg, init = paper
    f = jax.jit(make_logdensity(problem, cfg))
    x = jnp.asarray(init.x0[0])
    zeros = jnp.zeros((problem.posterior.op.n_interior, 3))
    nearby = x + jnp.asarray(init.sigma[0]) * jax.random.normal(jax.random.key(1), x.shape)
    guess = jax.block_until_ready(f(nearby, zeros))[1].interior
    lp, aux = jax.block_until_ready(f(x, guess))  # compiled here, not in the timed rounds
    assert np.isfinite(float(lp))
    benchmark.extra_info.update(nodes=len(problem.mesh.nodes), cg_iterations=int(aux.solve.iterations))
    benchmark(lambda: jax.block_until_ready(f(x, guess)))


def test_rwmh_step(benchmark, paper):
    problem, cfg, init = paper
    logdensity = make_logdensity(problem, cfg)
    dense = dense_preconditioning(problem, cfg)
    kernel = rwmh.build_kernel(logdensity, preconditioner=rw_preconditioner(problem, cfg) if dense else None)
    interior0 = jnp.zeros((problem.posterior.op.n_interior, 3))
    state = jax.jit(lambda x: rwmh.init(x, logdensity, interior0))(jnp.asarray(init.x0[0]))
    cache = jax.jit(kernel.init_cache)(state)
    sigma = tuple(jnp.asarray(s) for s in init.sigma)
    step = jax.jit(kernel.step)
    key = jax.random.key(2)
    _, info, _ = jax.block_until_ready(step(key, state, sigma, cache))
    benchmark.extra_info.update(nodes=len(problem.mesh.nodes), preconditioner="dense" if dense else "posterior's",
                                cg_iterations=int(info.cg_iterations))
    benchmark(lambda: jax.block_until_ready(step(key, state, sigma, cache)))


def test_nuts_transition(benchmark, data):
    # starts without the mode search (init.method=perturb): the search takes longer than the timing
    problem, cfg, init = _setup(data, "nuts", ["init.method=perturb"])
    s = cfg.sampler
    target = gradient_target(problem, cfg, init.center, init.sigma[0])
    kernel = gibbs.build_kernel(target, s.kind, max_num_doublings=s.max_tree_depth,
                                elastic_moves=s.elastic_moves)
    interior0 = jnp.zeros((problem.posterior.op.n_interior, 3))
    state, _ = jax.jit(lambda x: gibbs.init(target, x, interior0))(jnp.asarray(init.x0[0]))
    cache = jax.jit(kernel.init_cache)(state)
    nb3 = 3 * problem.posterior.n_boundary
    params = gibbs.GibbsParams(jnp.asarray(s.step_size), jnp.ones(nb3),
                               jnp.diag(jnp.asarray(init.sigma[1], jnp.float64)))
    step = jax.jit(kernel.step)
    key = jax.random.key(3)
    _, info, _ = jax.block_until_ready(step(key, state, params, cache))
    benchmark.extra_info.update(nodes=len(problem.mesh.nodes), elastic_moves=s.elastic_moves,
                                gradient_evaluations=int(info.grad_evals), tree_depth=int(info.tree_depth),
                                cg_iterations=int(info.cg_iterations))
    benchmark(lambda: jax.block_until_ready(step(key, state, params, cache)))

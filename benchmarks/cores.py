"""How the random walk's chains scale over this machine's cores.  (not part of the test suite)

The paper's experiment runs 3 chains on a 2-core CPU, and one chain alone does not run
twice as fast as each of two together.  This script says whether that is the way
``bayesreg.sampler.sample`` runs the chains (host threads in one process, one XLA runtime)
or the machine (two cores that share a cache, a memory bus and a host with other tenants).
Each chain runs the sampler's own chunk program (``sampler._build_chunk`` for one chain:
the paper's joint kernel with the chain's dense ``K_ii^-1`` built at the chunk's start,
as in the runs) on a run's problem, from the config's starts::

    python benchmarks/cores.py --problem RUN/checkpoint/problem.npz [--model three_compartment]

Three layouts, timed in turn in each of ``--rounds`` rounds (this machine's speed drifts
by up to 2x within minutes, so read the layouts of one round against each other):

* ``alone``: one chain in one process pinned to one core;
* ``processes``: ``--workers`` chains, one process each, each pinned to its own core, all
  started together once every one has compiled;
* ``threads``: the same chains in one process, one host thread each, not pinned (as
  ``sample`` runs whole chains).

Every worker process takes its XLA flags from ``bayesreg`` as the CLI does
(``--single-thread-eigen`` adds ``--xla_cpu_multi_thread_eigen=false``).  Each line gives
MH steps/s per chain, their total, and the total over the ``alone`` figure of the round:
what the extra cores add.  ``--out FILE.json`` keeps the figures.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def _worker(args) -> None:
    """One process: ``args.threads`` chains (``args.chain`` on), each timed over its chunks.

    Prints ``ready`` once compiled, waits for a line on stdin, then prints one JSON line.
    """
    if args.pin >= 0:
        os.sched_setaffinity(0, {args.pin})  # before JAX starts its thread pools
    if args.single_thread_eigen:
        os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "") + " --xla_cpu_multi_thread_eigen=false").strip()
    import threading

    from bayesreg import _xla

    _xla.configure()
    import jax
    import jax.numpy as jnp
    import numpy as np

    from bayesreg import pipeline
    from bayesreg.config import load_config
    from bayesreg.sampler import _build_chunk, build_kernel, init

    cfg = load_config(REPO / "configs" / f"paper_{args.model}.yaml")
    problem = pipeline.load_problem(args.problem, cfg)
    n_i = problem.posterior.op.n_interior
    logdensity = pipeline.make_logdensity(problem, cfg)
    kernel = build_kernel(logdensity, None, preconditioner=pipeline._preconditioner_rw(problem, cfg))
    start = pipeline.initialise(problem, cfg)
    x0 = np.asarray(start.x0)
    sigma = tuple(jnp.asarray(s) for s in start.sigma)
    chunk = _build_chunk(kernel, args.steps // 10, 10, 1)  # the sampler's program, thinning 10

    def state_of(c):
        st = init(jnp.asarray(x0[c % len(x0)]), logdensity, jnp.zeros((n_i, 3)))
        return jax.tree.map(lambda a: a[None], st)

    def run_chunk(c, j, st):
        st, out = chunk(jax.random.split(jax.random.fold_in(jax.random.key(c), j), 1), st, sigma)
        return st, [np.asarray(o) for o in out]

    chains = list(range(args.chain, args.chain + args.threads))
    states = {}
    for c in chains:  # compile (one shape: once) and run each chain's first chunk untimed
        states[c], _ = run_chunk(c, 0, state_of(c))
    print("ready", flush=True)
    sys.stdin.readline()
    results = {}

    def timed(c):
        st, acc, cg = states[c], [], []
        t = time.perf_counter()
        for j in range(1, args.chunks + 1):
            st, out = run_chunk(c, j, st)
            acc.append(out[3].mean())
            cg.append(out[4].mean())
        results[c] = {"chain": c, "steps_per_s": args.chunks * args.steps / (time.perf_counter() - t),
                      "acceptance": float(np.mean(acc)), "cg_iterations": float(np.mean(cg))}

    threads = [threading.Thread(target=timed, args=(c,)) for c in chains]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    print(json.dumps([results[c] for c in chains]), flush=True)


def _launch(args, *, pin: int, chain: int, threads: int) -> subprocess.Popen:
    cmd = [sys.executable, __file__, "--worker", "--problem", args.problem, "--model", args.model,
           "--pin", str(pin), "--chain", str(chain), "--threads", str(threads),
           "--chunks", str(args.chunks), "--steps", str(args.steps)]
    if args.single_thread_eigen:
        cmd.append("--single-thread-eigen")
    env = dict(os.environ)
    env.setdefault("JAX_COMPILATION_CACHE_DIR", args.cache)  # one compilation for all workers
    return subprocess.Popen(cmd, stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, cwd=REPO,
                            env=env)


def _line(p: subprocess.Popen, is_it) -> str:
    """The first line of a worker's output that ``is_it``; an error if it exits first."""
    for line in p.stdout:
        if is_it(line.strip()):
            return line
    p.wait()
    raise SystemExit(f"a worker exited with status {p.returncode} before it was done (its errors above)")


def _together(procs) -> list[dict]:
    """Wait until every worker has compiled, start them at once, collect their chains."""
    for p in procs:
        _line(p, lambda s: s == "ready")
    for p in procs:
        p.stdin.write("go\n")
        p.stdin.flush()
    out = []
    for p in procs:
        out += json.loads(_line(p, lambda s: s.startswith("[")))
        p.wait()
    return out


def main(argv=None) -> list[dict]:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--problem", required=True, help="a run's checkpoint/problem.npz")
    p.add_argument("--model", choices=("three_compartment", "uniform"), default="three_compartment",
                   help="the paper config the problem was run with")
    p.add_argument("--workers", type=int, default=None, help="chains run at once (default: the cores)")
    p.add_argument("--rounds", type=int, default=3)
    p.add_argument("--chunks", type=int, default=4, help="timed chunks per chain, after one untimed")
    p.add_argument("--steps", type=int, default=1000, help="steps per chunk (a multiple of 10)")
    p.add_argument("--single-thread-eigen", action="store_true",
                   help="XLA_FLAGS=--xla_cpu_multi_thread_eigen=false in every worker")
    p.add_argument("--out", help="write the figures as JSON here")
    p.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    p.add_argument("--pin", type=int, default=-1, help=argparse.SUPPRESS)
    p.add_argument("--chain", type=int, default=0, help=argparse.SUPPRESS)
    p.add_argument("--threads", type=int, default=1, help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.rounds < 1 or args.chunks < 1:
        p.error("--rounds and --chunks must be >= 1")
    if args.steps % 10 or args.steps < 10:
        p.error("--steps must be a positive multiple of 10 (the sampler's thinning)")
    if not hasattr(os, "sched_setaffinity"):
        p.error("needs os.sched_setaffinity (Linux) to pin a process to a core")
    if args.worker:
        _worker(args)
        return []
    if not Path(args.problem).is_file():
        p.error(f"--problem: no file {args.problem}")
    args.problem = str(Path(args.problem).resolve())  # the workers run in the repository root
    cores = sorted(os.sched_getaffinity(0))
    workers = args.workers or len(cores)
    if not 2 <= workers <= len(cores):
        p.error(f"--workers must be between 2 and the {len(cores)} cores available")
    rows = []
    with tempfile.TemporaryDirectory(prefix="bayesreg-cores-") as cache:
        args.cache = cache
        print(f"{args.model} on {args.problem}: {workers} chains at once on {len(cores)} cores, "
              f"{args.chunks} x {args.steps} steps per chain", flush=True)
        for r in range(1, args.rounds + 1):
            alone = _together([_launch(args, pin=cores[0], chain=0, threads=1)])
            procs = _together([_launch(args, pin=cores[w], chain=w, threads=1) for w in range(workers)])
            threaded = _together([_launch(args, pin=-1, chain=0, threads=workers)])
            base = alone[0]["steps_per_s"]
            for layout, chains in (("alone", alone), ("processes", procs), ("threads", threaded)):
                rates = [c["steps_per_s"] for c in chains]
                row = {"round": r, "layout": layout, "steps_per_s_per_chain": rates, "total": sum(rates),
                       "total_over_alone": sum(rates) / base,
                       "acceptance": [c["acceptance"] for c in chains],
                       "cg_iterations": [c["cg_iterations"] for c in chains]}
                rows.append(row)
                print(f"round {r} {layout:>9}: " + ", ".join(f"{x:.0f}" for x in rates)
                      + f" steps/s per chain, {row['total']:.0f} in total ({row['total_over_alone']:.2f}x alone)",
                      flush=True)
        if args.out:  # written whole, then moved into place
            tmp = Path(f"{args.out}.tmp-{os.getpid()}")
            tmp.write_text(json.dumps({"problem": args.problem, "model": args.model,
                                       "workers": workers, "rows": rows}, indent=1))
            os.replace(tmp, args.out)
    return rows


if __name__ == "__main__":
    main()

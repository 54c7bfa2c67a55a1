"""Where a sampler step's time goes: a profile of the running chains, split by part.

Timing the solve or the similarity alone, in a loop of its own, misses what they cost inside
a step (with the other chains' threads on the other cores and each other's data in the
caches).  This script runs the chains as ``benchmarks/run.py`` does (same problem, starts,
kernel and chunks), times one chunk, then records one more under :func:`jax.profiler` and
files the time of every XLA operation under the part of the step it was compiled from, by
the :func:`jax.named_scope` names that the log-density and the random walk carry
(``benchmarks/profiling.py``): stiffness, solve, similarity, strain energy, constraints,
proposal, accept, cache build (each chain's preconditioner at its chunk's start), control
flow and the rest.  The proposal and accept scopes are the random walk's: under
``--kernel nuts`` what lies outside the log-density's scopes (the trajectory's own
arithmetic, the tree building) counts as "other".

Run from the repository root, on an otherwise idle machine::

    python benchmarks/profile_step.py                       # paper kernel, 16 mm mesh, 3 chains
    python benchmarks/profile_step.py --mesh 26@3 --chains 1 --top 12
    python benchmarks/profile_step.py --kernel nuts --mesh 24
    python benchmarks/profile_step.py --kernel nuts --run runs/paper_brainweb/s5   # a run's own problem

It prints, per part, the operations' time summed over the threads per step (ms) and its
share, the wall time per step, and ``busy`` (seconds of operations per second profiled: on a
CPU the mean number of busy threads; on a GPU the share of the time the device works).  The
profiler holds every event in memory (about 1 kB each), so on a CPU at most ``--seconds``
of the chunk are recorded, in a window opened a third of the way in (past the chunk-start
builds); the steps of such a window are estimated from the chunk's rate.  The profiled
chunk runs somewhat slower than the timed one (its wall time per step is printed beside).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import profiling  # noqa: E402  (benchmarks/profiling.py)

# before JAX starts its backend (XLA reads XLA_FLAGS once); importing bayesreg starts nothing
_DUMP = profiling.enable_hlo_dump()

import run  # noqa: E402  (benchmarks/run.py)


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--kernel", choices=run.KERNELS, default="rwmh")
    p.add_argument("--mesh", default="16", help="EDGE[@RESOLUTION] in mm (default 16: the paper's size)")
    p.add_argument("--run", type=Path, default=None, metavar="RUN_DIR",
                   help="profile the problem, config and starts a run's checkpoint holds (e.g. a "
                   "1 mm BrainWeb run of the paper's size) instead of --mesh's")
    p.add_argument("--chains", type=int, default=3)
    p.add_argument("--chain-method", default="auto", choices=run.chains.CHAIN_METHODS)
    p.add_argument("--rw-chunk-steps", type=int, default=1000, help="random-walk steps per chunk")
    p.add_argument("--nuts-chunk", type=int, default=10, help="NUTS transitions per chunk")
    p.add_argument("--nuts-warmup", type=int, default=60, help="NUTS warm-up transitions per chain")
    p.add_argument("--seconds", type=float, default=2.0,
                   help="profile at most this long on a CPU (a window of the chunk)")
    p.add_argument("--top", type=int, default=0, help="also list the N costliest operations")
    p.add_argument("--keep", type=Path, default=None, metavar="DIR",
                   help="keep the trace (TensorBoard's profile plugin opens it) and the step's HLO")
    p.add_argument("--cache", type=Path, default=run.REPO / "benchmarks" / ".cache")
    p.add_argument("--out", type=Path, help="write the figures as JSON")
    args = p.parse_args(argv)
    args.timed_chunks, args.time_target_s = 1, 0.5

    run.bayesreg.configure_jax()
    if args.run is not None:
        try:
            cfg, problem, init = run.run_problem(args.run, args.kernel)
        except ValueError as exc:
            p.error(f"{exc} (give --kernel to match)")
        if len(init.x0) != args.chains:
            p.error(f"--run {args.run} has {len(init.x0)} chains: give --chains {len(init.x0)}")
    else:
        edge, res = run.parse_mesh(args.mesh)
        data, _ = run.problem_data(edge, res, args.cache)
        cfg = run.with_chains(run.kernel_config(args.kernel, edge, res), max(2, min(args.chains, 16)))
        problem = run.assemble(cfg, data)
        init = run.initialise(problem, cfg)
    if args.kernel == "rwmh":
        at = run.rwmh_setup(problem, cfg, init, args)
    else:
        at, _ = run.nuts_setup(problem, cfg, init, args)
    row, run_args = at(args.chains)
    profiler = profiling.ChunkProfiler(_DUMP, max_seconds=args.seconds)
    try:
        row.update(run.run_chunks(*run_args, profiler=profiler))
        steps_per_chunk = run_args[4] * run_args[5]  # draws x thinning
        split = profiler.split(args.chains * steps_per_chunk, row["steps_per_s_total"])
        top = []
        if args.top:  # the costliest operations, from the same trace
            index = profiling.hlo_index(_DUMP)
            prof = profiling.split_profile(profiler.trace_dir, index, profiling.step_programs(index) or None)
            for (program, op), ns in prof["per_op_ns"].most_common(args.top):
                _, name, control = index.get((program, op), ("?", "?", False))
                part = profiling.CONTROL if control else profiling.part_of(name)
                top.append((ns / 1e6 / split["steps_profiled"], part, op, name[-90:]))
        if args.keep is not None:
            profiler.close(keep=args.keep / "trace")
            profiling.keep_hlo(_DUMP, args.keep / "hlo")
    finally:
        profiler.close()
        profiling.remove(_DUMP)
    # a whole profiled chunk has its own rate; a window's steps were estimated from the timed one
    profiled_ms = (None if split["steps_estimated"] else
                   1e3 * row["profiled_chunk_s"] * args.chains / split["steps_profiled"])
    out = {"row": row, "nodes": len(problem.mesh.nodes), **split,
           "wall_ms_per_step_per_chain": 1e3 / row["steps_per_s_per_chain"],
           "profiled_wall_ms_per_step_per_chain": profiled_ms}
    print(f"\n{args.kernel}, {len(problem.mesh.nodes)} nodes, {args.chains} chains ({row['chain_method']}, "
          f"{row['preconditioner']} CG): operations' time per step, summed over threads")
    print("| part | ms per step | share |")
    print("|---|---|---|")
    for k in profiling.order():
        print(f"| {k} | {split['ms_per_step'][k]:.3f} | {100 * split['share'].get(k, 0):.0f}% |")
    print(f"| all operations | {split['op_ms_per_step_total']:.3f} | 100% |")
    profiled = (f"{profiled_ms:.3f} profiled" if profiled_ms is not None else
                f"a {split['window_s']:.1f} s window profiled")
    print(f"\nwall ms per step per chain: {out['wall_ms_per_step_per_chain']:.3f} timed, "
          f"{profiled}; busy {split['busy']:.2f}; "
          f"operations with no HLO found: {split['unmatched_ms_per_step']:.3f} ms per step")
    if top:
        print(f"\nThe {args.top} costliest operations (ms per step, part, instruction, op_name):")
        for ms, part, op, name in top:
            print(f"  {ms:8.4f}  {part:14s} {op:32s} {name}")
    if args.out:
        args.out.write_text(json.dumps(out, indent=2, default=float))
    return out


if __name__ == "__main__":
    main()

"""Where the time of one MH step goes: a profile of the sampler's compiled chunks.

``run.py``'s figure 2 times the solve, the similarity and the log-density each alone in a
loop of their own; figure 2b and this script measure the split inside the step instead.
This script runs :func:`bayesreg.sampler.sample` as ``steps.py`` does (same problem, states,
keys and chunks), records it with :func:`jax.profiler.trace`, and attributes the time of
every XLA operation of the chunk programs to the part of the step it was compiled from,
through the :func:`jax.named_scope` names that the log-density and the kernel carry and the
compiled programs' HLO (``benchmarks/profiling.py``).  So the parts are timed where they run:
with the other chains' threads on the other core, and with each other's data in the caches.

Run from the repository root, on an otherwise idle machine (not part of the test suite)::

    python benchmarks/profile_step.py                  # 3 chains, tuned states (steps.py's)
    python benchmarks/profile_step.py --chains 2 --from-starts --model uniform

Any ``steps.py`` option is passed on (``--model``, ``--from-starts``, ``--chains``,
``--chunks``, ``--problem``).  It prints, per part, the time summed over the threads per MH
step (ms) and its share, and the wall time per step; ``--out FILE.json`` writes them.

What is counted is ``profiling.py``'s: each operation's exclusive time, summed over threads
(see its docstring).  The profile covers every chunk of the ``sample`` call, the compiling
one included; the wall time per step is that of the timed chunks, under the profiler, which
adds a few percent.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import profiling  # noqa: E402  (benchmarks/profiling.py)

_DUMP = profiling.enable_hlo_dump()  # before JAX starts its backend (bayesreg adds its own flag)
import steps  # noqa: E402  (benchmarks/steps.py)

from profiling import CONTROL, hlo_index, part_of, per_step, split_profile, step_programs  # noqa: E402


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], add_help=True)
    p.add_argument("--out", type=Path, help="write the figures as JSON")
    p.add_argument("--top", type=int, default=0, help="also list the N costliest operations")
    p.add_argument("--keep", action="store_true",
                   help="keep the profile and the HLO dump (their folders are in the JSON)")
    args, rest = p.parse_known_args(argv)
    profiler = profiling.ChunkProfiler(_DUMP, max_seconds=None)  # the whole sample() call

    @contextlib.contextmanager
    def around_sampling():
        profiler.start()
        try:
            yield
        finally:
            profiler.stop()

    run = steps.main(rest, around_sampling=around_sampling)
    index = hlo_index(_DUMP)
    prof = split_profile(profiler.trace_dir, index, step_programs(index) or None)
    n_steps = run["chains"] * run["steps_total_per_chain"]
    order = profiling.order()
    out = {"steps_run": run,
           "kept": {"dump_dir": _DUMP, "trace_dir": profiler.trace_dir} if args.keep else None,
           **per_step(prof, n_steps),
           "wall_ms_per_step_per_chain": 1e3 / run["steps_per_s_per_chain"]}
    print(f"\nOperation time per MH step, summed over threads ({run['chains']} chains, "
          f"{n_steps} steps profiled, all chunks including the first):")
    print("| part | ms per step | share |")
    print("|---|---|---|")
    for k in order:
        print(f"| {k} | {out['ms_per_step'][k]:.3f} | {100 * out['share'].get(k, 0):.0f}% |")
    print(f"| all operations | {out['op_ms_per_step_total']:.3f} | 100% |")
    print(f"\nwall time per step per chain (the timed chunks, under the profiler): "
          f"{out['wall_ms_per_step_per_chain']:.3f} ms; operations with no HLO found: "
          f"{out['unmatched_ms_per_step']:.3f} ms per step")
    if args.top:
        print(f"\nThe {args.top} costliest operations (ms per step, part, op_name):")
        for (program, op), v in prof["per_op_ns"].most_common(args.top):
            _, name, control = index.get((program, op), ("?", "?", False))
            part = CONTROL if control else part_of(name)
            print(f"  {v / 1e6 / n_steps:8.4f}  {part:14s} {op:32s} {name[-90:]}")
    if args.out:
        args.out.write_text(json.dumps(out, indent=2))
    if not args.keep:
        profiler.close()
        profiling.remove(_DUMP)
    return out


if __name__ == "__main__":
    main()

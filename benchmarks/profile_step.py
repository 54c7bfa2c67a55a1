"""Where the time of one MH step goes: a profile of the sampler's compiled chunks.

``run.py``'s "time split" times the solve, the similarity and the log-density each alone in a
loop of their own, so its "rest of the step" is whatever the pieces did not add up to (66% of
a one-chain step at the paper's size, and negative on the 9,989-node mesh, where the pieces
alone were slower than the step).  This script measures the split inside the step instead:
it runs :func:`bayesreg.sampler.sample` as ``steps.py`` does (same problem, states, keys and
chunks), records it with :func:`jax.profiler.trace`, and attributes the time of every XLA
operation of the chunk programs to the part of the step it was compiled from, through the
:func:`jax.named_scope` names that the log-density and the kernel carry
(:data:`bayesreg.posterior.SCOPES`, :data:`bayesreg.sampler.PROPOSAL_SCOPE`,
:data:`bayesreg.sampler.ACCEPT_SCOPE`) and the compiled programs' HLO (dumped with
``--xla_dump_to``).  So the parts are timed where they run: with the other chains'
threads on the other core, and with each other's data in the caches.

Run from the repository root, on an otherwise idle machine (not part of the test suite)::

    python benchmarks/profile_step.py                  # 3 chains, tuned states (steps.py's)
    python benchmarks/profile_step.py --chains 2 --from-starts --model uniform

Any ``steps.py`` option is passed on (``--model``, ``--from-starts``, ``--chains``,
``--chunks``, ``--problem``).  It prints, per part, the time summed over the threads per MH
step (ms) and its share, and the wall time per step; ``--out FILE.json`` writes them.

What is counted: the exclusive time of each operation (an event's duration less that of
the events nested in it on the same thread), so that a ``conditional`` or a ``while``
executed by the runtime counts only its own overhead, filed as "control flow"; a small
``while`` that XLA:CPU compiles into one kernel (``xla_cpu_small_call``, the CG loop)
counts whole, under the scope it was called from.  The time of operations summed over
threads exceeds the wall time where XLA runs independent operations of one chain on both
cores at once; the profiler itself adds a few percent.
"""

from __future__ import annotations

import argparse
import collections
import glob
import json
import os
import re
import shutil
import sys
import tempfile
import warnings
from pathlib import Path

_DUMP = tempfile.mkdtemp(prefix="bayesreg-hlo-")
# before JAX starts its backend (bayesreg adds its own flag to these)
os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "")
                           + f" --xla_dump_to={_DUMP} --xla_dump_hlo_as_text").strip()

sys.path.insert(0, str(Path(__file__).resolve().parent))
import steps  # noqa: E402  (benchmarks/steps.py)

from bayesreg import _xla  # noqa: E402

_xla.configure()
import jax  # noqa: E402

from bayesreg.posterior import SCOPES  # noqa: E402
from bayesreg.sampler import ACCEPT_SCOPE, PROPOSAL_SCOPE  # noqa: E402

#: part of the step -> the named scope it was compiled under (these scopes do not nest: an
#: operation's op_name holds at most one of them, under the jit/scan/cond path around it)
PARTS = dict(SCOPES)
PARTS["proposal"] = PROPOSAL_SCOPE
PARTS["accept"] = ACCEPT_SCOPE
CONTROL = "control flow"
OTHER = "other"

_INSTR = re.compile(r"^\s*(?:ROOT\s+)?%([^\s=]+)\s*=\s*(.*)$")
_OP_NAME = re.compile(r'op_name="([^"]*)"')


def hlo_index(dump_dir: str) -> dict:
    """``(program id, instruction) -> (module name, op_name metadata, is control flow)``
    from the after-optimisation HLO text that XLA dumped (``module_<program id>.<name>...``;
    the profile's events carry the same ``program_id``, so programs of one name, such as
    the chunk compiled for two shapes, stay apart).

    An instruction that XLA made without metadata (the per-group combination of the
    stiffness blocks comes out as ``dot`` instructions with none) takes that of the nearest
    instruction using its result that has one.
    """
    index = {}
    for path in glob.glob(os.path.join(dump_dir, "*after_optimizations.txt")):
        text = Path(path).read_text()
        head = re.match(r"HloModule\s+([^\s,]+)", text)
        number = re.match(r"module_(\d+)\.", os.path.basename(path))
        if not head or not number:
            continue
        module, program = head.group(1), int(number.group(1))
        names, users = {}, collections.defaultdict(list)
        for line in text.splitlines():
            m = _INSTR.match(line)
            if not m:
                continue
            name, rest = m.group(1), m.group(2)
            op = _OP_NAME.search(rest)
            small = 'xla_cpu_small_call="true"' in rest
            control = (not small) and bool(re.search(r"\s(conditional|while|call)\(", rest))
            names[name] = (op.group(1) if op else "", control)
            for operand in set(re.findall(r"%([^\s,()=]+)", rest.split(" metadata=")[0])):
                users[operand].append(name)
        for name, (op, control) in names.items():
            seen, queue = {name}, list(users.get(name, ()))
            while not op and queue:  # breadth-first over the users
                user = queue.pop(0)
                if user in seen or user not in names:
                    continue
                seen.add(user)
                op = names[user][0]
                queue.extend(users.get(user, ()))
            index[(program, name)] = (module, op, control)
    return index


def part_of(op_name: str) -> str:
    for name, scope in PARTS.items():
        if scope in op_name:
            return name
    return OTHER


def split_profile(trace_dir: str, index: dict, modules: set | None = None) -> dict:
    """Exclusive time (ns) per part, summed over threads, of the XLA operations in the
    profile under ``trace_dir`` (only those of the programs named in ``modules`` where
    given)."""
    path = glob.glob(os.path.join(trace_dir, "**", "*.xplane.pb"), recursive=True)
    if not path:
        raise RuntimeError(f"no profile written under {trace_dir}")
    data = jax.profiler.ProfileData.from_file(path[0])
    totals = collections.Counter()
    per_op = collections.Counter()
    for plane in data.planes:
        for line in plane.lines:
            events = []
            for ev in line.events:
                with warnings.catch_warnings():  # jaxlib's event_stats type, on iteration
                    warnings.simplefilter("ignore", DeprecationWarning)
                    stats = dict(ev.stats)
                if "hlo_op" not in stats:
                    continue
                if modules is not None and stats.get("hlo_module", "") not in modules:
                    continue
                program = int(stats.get("program_id", -1))
                events.append((ev.start_ns, ev.start_ns + ev.duration_ns, program, stats["hlo_op"]))
            events.sort(key=lambda e: (e[0], -e[1]))
            # exclusive time: subtract the events directly nested in each one (same thread)
            stack: list[list] = []
            done = []
            for start, end, program, op in events:
                while stack and stack[-1][1] <= start:
                    done.append(stack.pop())
                if stack:
                    stack[-1][4] += min(end, stack[-1][1]) - start
                stack.append([start, end, program, op, 0])
            done.extend(stack)
            for start, end, program, op, nested in done:
                own = max(0, (end - start) - nested)
                info = index.get((program, op))
                per_op[(program, op)] += own
                if info is None:
                    totals[OTHER] += own
                elif info[2]:
                    totals[CONTROL] += own
                else:
                    totals[part_of(info[1])] += own
    unmatched = sum(v for key, v in per_op.items() if key not in index)
    return {"ns": dict(totals), "unmatched_ns": unmatched, "per_op_ns": per_op}


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], add_help=True)
    p.add_argument("--out", type=Path, help="write the figures as JSON")
    p.add_argument("--top", type=int, default=0, help="also list the N costliest operations")
    p.add_argument("--keep", action="store_true",
                   help="keep the profile and the HLO dump (their folders are in the JSON)")
    args, rest = p.parse_known_args(argv)
    trace_dir = tempfile.mkdtemp(prefix="bayesreg-trace-")
    options = jax.profiler.ProfileOptions()
    options.python_tracer_level = 0  # XLA's operations only (Python tracing slows the run)

    def around_sampling():
        return jax.profiler.trace(trace_dir, profiler_options=options)

    run = steps.main(rest, around_sampling=around_sampling)
    index = hlo_index(_DUMP)
    chunk_modules = {m for m, _, _ in index.values() if m.startswith("jit_mapped")}
    prof = split_profile(trace_dir, index, chunk_modules or None)
    n_steps = run["chains"] * run["steps_total_per_chain"]
    ns = prof["ns"]
    total = sum(ns.values())
    order = list(PARTS) + [CONTROL, OTHER]
    out = {
        "steps_run": run,
        "kept": {"dump_dir": _DUMP, "trace_dir": trace_dir} if args.keep else None,
        "ms_per_step": {k: ns.get(k, 0) / 1e6 / n_steps for k in order},
        "share": {k: ns.get(k, 0) / total for k in order} if total else {},
        "op_ms_per_step_total": total / 1e6 / n_steps,
        "unmatched_ms_per_step": prof["unmatched_ns"] / 1e6 / n_steps,
        "wall_ms_per_step_per_chain": 1e3 / run["steps_per_s_per_chain"],
    }
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
        for folder in (trace_dir, _DUMP):
            shutil.rmtree(folder, ignore_errors=True)
    return out


if __name__ == "__main__":
    main()

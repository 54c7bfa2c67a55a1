"""The time of a step, split by part, from a profile of the sampler's compiled programs.

Shared by ``profile_step.py`` and ``run.py``'s figure 2b.  The log-density and the random
walk carry :func:`jax.named_scope` names (:data:`bayesreg.posterior.SCOPES`,
:data:`bayesreg.sampler.PROPOSAL_SCOPE`, :data:`bayesreg.sampler.ACCEPT_SCOPE`,
:data:`bayesreg.sampler.CACHE_SCOPE`) into the
``op_name`` metadata of the optimised HLO.  A :func:`jax.profiler` trace names, for each
operation it ran, the HLO instruction and the program (``hlo_op``, ``program_id``); the HLO
that XLA dumps (``--xla_dump_to``, :func:`enable_hlo_dump`) maps the instruction to its
metadata, so every operation's time is filed under the part of the step it was compiled
from, measured where it ran: beside the other chains' threads, with each other's data in the
caches.

What is counted: the exclusive time of each operation (an event's duration less that of the
events nested in it on the same thread), so that a ``conditional`` or a ``while`` executed by
the runtime counts only its own overhead, filed as "control flow"; a small ``while`` that
XLA:CPU compiles into one kernel (``xla_cpu_small_call``, the CG loop) counts whole, under the
scope it was called from.  Summed over threads, the operations' time exceeds the wall time
where XLA runs independent operations of one chain on both cores at once.
"""

from __future__ import annotations

import collections
import glob
import os
import re
import shutil
import sys
import tempfile
import threading
import time
import warnings
from pathlib import Path

CONTROL = "control flow"
OTHER = "other"

_INSTR = re.compile(r"^\s*(?:ROOT\s+)?%([^\s=]+)\s*=\s*(.*)$")
_OP_NAME = re.compile(r'op_name="([^"]*)"')


def enable_hlo_dump() -> str:
    """Make XLA dump every compiled program's HLO as text into a new temporary folder
    (returned).  Must run before JAX starts its backend (XLA reads ``XLA_FLAGS`` once),
    so before :mod:`bayesreg` is imported.

    Raises
    ------
    RuntimeError
        A JAX backend has already started (its programs would not be dumped).
    """
    # (not through bayesreg, whose import starts the backend: BlackJAX computes at import)
    if "jax" in sys.modules:
        from jax._src import xla_bridge

        if xla_bridge.backends_are_initialized():
            raise RuntimeError("enable_hlo_dump() after JAX started its backend: XLA would "
                               "not dump the programs; call it before importing bayesreg")
    folder = tempfile.mkdtemp(prefix="bayesreg-hlo-")
    os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "")
                               + f" --xla_dump_to={folder} --xla_dump_hlo_as_text").strip()
    return folder


def parts() -> dict:
    """Part of the step -> the named scope it was compiled under.  The scopes do not nest
    (the log-density's and the kernel's; the cache build holds no log-density): an
    operation's ``op_name`` holds at most one of them, under the jit/scan/cond path."""
    from bayesreg.posterior import SCOPES
    from bayesreg.sampler import ACCEPT_SCOPE, CACHE_SCOPE, PROPOSAL_SCOPE

    out = dict(SCOPES)
    out["proposal"] = PROPOSAL_SCOPE
    out["accept"] = ACCEPT_SCOPE
    out["cache build"] = CACHE_SCOPE  # each chain's K_ii^-1 (or condensation) per chunk
    return out


def order() -> list[str]:
    """The parts in the order the tables list them, then control flow and the rest."""
    return list(parts()) + [CONTROL, OTHER]


def part_of(op_name: str, scopes: dict | None = None) -> str:
    """The part whose scope ``op_name`` holds (``scopes``: :func:`parts`, given by a caller
    that asks for many), else "other"."""
    for name, scope in (scopes or parts()).items():
        if scope in op_name:
            return name
    return OTHER


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


def step_programs(index: dict) -> set[int]:
    """Ids of the programs that hold a part of the step (a named scope): the sampler's
    chunks, not the diagnostics or the setup around them."""
    scopes = tuple(parts().values())
    return {program for (program, _), (_, op, _) in index.items()
            if any(s in op for s in scopes)}


def split_profile(trace_dir: str, index: dict, programs: set[int] | None = None) -> dict:
    """Exclusive time (ns) per part, summed over threads, of the XLA operations in the
    profile under ``trace_dir`` (only those of the programs in ``programs`` where given).

    Returns ``{"ns": {part: ns}, "unmatched_ns": ns of operations with no HLO found,
    "per_op_ns": Counter((program id, instruction) -> ns)}``.

    Raises
    ------
    RuntimeError
        No profile was written under ``trace_dir``.
    """
    import jax

    path = glob.glob(os.path.join(trace_dir, "**", "*.xplane.pb"), recursive=True)
    if not path:
        raise RuntimeError(f"no profile written under {trace_dir}")
    data = jax.profiler.ProfileData.from_file(path[0])
    # where the operations ran: the host's threads on a CPU; on an accelerator its own
    # planes (the host's launch events there carry the same names and would count twice)
    device = jax.default_backend() != "cpu"
    first_program = {}
    for program, op in sorted(index):
        first_program.setdefault((index[(program, op)][0], op), program)
    scopes = parts()  # each instruction's part, once (not once per event)
    part_at = {key: CONTROL if control else part_of(name, scopes)
               for key, (_, name, control) in index.items()}
    totals = collections.Counter()
    per_op = collections.Counter()
    for plane in data.planes:
        if plane.name.startswith("/device:") != device:
            continue
        for line in plane.lines:
            events = []
            for ev in line.events:
                with warnings.catch_warnings():  # jaxlib's event_stats type, on iteration
                    warnings.simplefilter("ignore", DeprecationWarning)
                    stats = dict(ev.stats)
                if "hlo_op" not in stats:
                    continue
                if "program_id" in stats:
                    program = int(stats["program_id"])
                else:  # no program id on the event: the first program of its module's name
                    program = first_program.get((stats.get("hlo_module"), stats["hlo_op"]), -1)
                if programs is not None and program not in programs:
                    continue
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
                per_op[(program, op)] += own
                totals[part_at.get((program, op), OTHER)] += own
    unmatched = sum(v for key, v in per_op.items() if key not in index)
    return {"ns": dict(totals), "unmatched_ns": unmatched, "per_op_ns": per_op}


def per_step(prof: dict, n_steps: int) -> dict:
    """Milliseconds per MH step of each part (summed over threads), their shares, the
    operations' total and the unmatched time, from :func:`split_profile`."""
    ns = prof["ns"]
    total = sum(ns.values())
    names = order()
    return {
        "ms_per_step": {k: ns.get(k, 0) / 1e6 / n_steps for k in names},
        "share": {k: ns.get(k, 0) / total for k in names} if total else {},
        "op_ms_per_step_total": total / 1e6 / n_steps,
        "unmatched_ms_per_step": prof["unmatched_ns"] / 1e6 / n_steps,
    }


class ChunkProfiler:
    """Profile a stretch of a run (:func:`jax.profiler.start_trace` / ``stop_trace``, Python
    tracing off) and split it by part.  ``dump_dir`` is :func:`enable_hlo_dump`'s folder.

    ``start(expected_s)`` and ``stop()`` bracket the chunk to profile.  The profiler keeps
    every event in memory until it stops (about 1 kB each: a 90-second chunk of 64 chains
    at the paper's size took 8.5 GB), so a profile lasts at most ``max_seconds`` (``None``:
    no limit).  A chunk expected to last longer (``expected_s``, the timed chunks' length)
    is profiled in a window of ``max_seconds`` that opens a third of the way in, past the
    chains' chunk-start cache builds, so that the window holds steps only; a timer thread
    opens and closes it while the chunk runs.  ``split(n_steps, steps_per_s)`` reads the
    trace and the HLO dumped so far, keeps the step's programs (:func:`step_programs`) and
    returns :func:`per_step`'s figures over ``n_steps`` (all chains' steps of the chunk)
    where the whole chunk was profiled, else over the steps that ``steps_per_s`` (all
    chains' rate over the chunk, builds included: the builds are at most about a tenth of a
    chunk in ``run.py``) gives for the window (``"window_s"``, ``"steps_estimated"`` in the
    result).  ``close()`` removes the trace (the dump stays for the next profile;
    :func:`remove` deletes a folder).
    """

    def __init__(self, dump_dir: str, max_seconds: float | None = 1.0, on_begin=None):
        self.dump_dir = dump_dir
        self.max_seconds = max_seconds
        self.on_begin = on_begin  # called as the profile opens (run.py: keep the peak RSS so far)
        self.trace_dir = None
        self.running = False
        self.window = False  # a window of the chunk, not the whole of it
        self.window_s = None
        self._lock = threading.Lock()
        self._timers = []
        self._t0 = None
        self._closed = False

    def start(self, expected_s: float | None = None) -> None:
        self.trace_dir = tempfile.mkdtemp(prefix="bayesreg-trace-")
        if self.max_seconds is None:
            self._begin()
            return
        delay = 0.0
        if expected_s is not None and expected_s > 1.5 * self.max_seconds:
            delay, self.window = expected_s / 3, True
        else:
            self._begin()
        for at, fn in ((delay, self._begin), (delay + self.max_seconds, self._end)):
            if at > 0:
                t = threading.Timer(at, fn)
                t.daemon = True
                t.start()
                self._timers.append(t)

    def _begin(self) -> None:
        import jax

        with self._lock:
            if self.running or self._closed or self.window_s is not None:
                return
            if self.on_begin is not None:
                self.on_begin()
            options = jax.profiler.ProfileOptions()
            options.python_tracer_level = 0  # XLA's operations only (Python tracing slows the run)
            jax.profiler.start_trace(self.trace_dir, profiler_options=options)
            self._t0 = time.perf_counter()
            self.running = True

    def _end(self, at_chunk_end: bool = False) -> None:
        import jax

        with self._lock:
            self._closed = True  # a window not yet opened stays shut
            if not self.running:
                return
            self.window_s = time.perf_counter() - self._t0
            jax.profiler.stop_trace()
            self.running = False
            self.window = self.window or not at_chunk_end

    def stop(self) -> None:
        """End the profile at the end of the profiled chunk (if its window has not)."""
        for t in self._timers:
            t.cancel()
        self._end(at_chunk_end=True)

    def split(self, n_steps: int, steps_per_s: float) -> dict:
        """Per-step figures of the profile (:func:`per_step`), with the window's length.

        Raises
        ------
        RuntimeError
            Nothing was profiled (the chunk ended before its window opened).
        """
        if self.window_s is None:
            raise RuntimeError("the chunk ended before its profile window opened")
        index = hlo_index(self.dump_dir)
        prof = split_profile(self.trace_dir, index, step_programs(index) or None)
        steps = steps_per_s * self.window_s if self.window else n_steps
        return {**per_step(prof, steps), "window_s": self.window_s, "steps_estimated": self.window,
                "steps_profiled": steps}

    def close(self) -> None:
        self.stop()
        if self.trace_dir:
            remove(self.trace_dir)
            self.trace_dir = None


def remove(folder: str | None) -> None:
    if folder:
        shutil.rmtree(folder, ignore_errors=True)

"""The time of a step, split by part, from a profile of the sampler's compiled programs.

Used by ``profile_step.py``.  The log-density and the random
walk carry :func:`jax.named_scope` names (:data:`bayesreg.model.posterior.SCOPES`,
:data:`bayesreg.sampling.kernels.rwmh.PROPOSAL_SCOPE`, :data:`bayesreg.sampling.kernels.rwmh.ACCEPT_SCOPE`,
:data:`bayesreg.sampling.kernels.rwmh.CACHE_SCOPE`) into the
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

On a GPU the device's own kernels and copies are read instead (the host's launch events
would count them twice), the kernels inside command buffers by their own names
(:func:`split_profile`), and a chunk is profiled whole, with the device idle at the
trace's start and stop (:class:`ChunkProfiler`).
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
_COMPUTATION = re.compile(r"^(?:ENTRY\s+)?%([^\s(]+)\s*\(.*\{\s*$")
_CALLS = re.compile(r"\bcalls=%([^\s,}]+)")


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
    from bayesreg.model.posterior import SCOPES
    from bayesreg.sampling.kernels.rwmh import ACCEPT_SCOPE, CACHE_SCOPE, PROPOSAL_SCOPE

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


def _dumped(dump_dir: str) -> dict[int, str]:
    """Program id -> its after-optimisation HLO text (``module_<program id>.<name>...``)
    among the files that XLA dumped into ``dump_dir``."""
    out = {}
    for path in glob.glob(os.path.join(dump_dir, "*after_optimizations.txt")):
        number = re.match(r"module_(\d+)\.", os.path.basename(path))
        if number:
            out[int(number.group(1))] = path
    return out


def hlo_index(dump_dir: str) -> dict:
    """``(program id, instruction) -> (module name, op_name metadata, is control flow)``
    from the after-optimisation HLO text that XLA dumped (``module_<program id>.<name>...``;
    the profile's events carry the same ``program_id``, so programs of one name, such as
    the chunk compiled for two shapes, stay apart).

    An instruction that XLA made without metadata takes that of the computation it calls
    (a GPU fusion: the root of its fused computation, else the first of its instructions
    that has one), else that of the nearest instruction using its result that has one (the
    per-group combination of the stiffness blocks comes out as ``dot`` instructions with
    none on a CPU).
    """
    index = {}
    for program, path in _dumped(dump_dir).items():
        text = Path(path).read_text()
        head = re.match(r"HloModule\s+([^\s,]+)", text)
        if not head:
            continue
        module = head.group(1)
        names, users = {}, collections.defaultdict(list)
        calls, computation_ops = {}, collections.defaultdict(list)  # root's op_name first
        computation = None
        for line in text.splitlines():
            start = _COMPUTATION.match(line)
            if start:
                computation = start.group(1)
                continue
            m = _INSTR.match(line)
            if not m:
                continue
            name, rest = m.group(1), m.group(2)
            op = _OP_NAME.search(rest)
            small = 'xla_cpu_small_call="true"' in rest
            control = (not small) and bool(re.search(r"\s(conditional|while|call)\(", rest))
            names[name] = (op.group(1) if op else "", control)
            if op and computation is not None:
                if line.lstrip().startswith("ROOT"):
                    computation_ops[computation].insert(0, op.group(1))
                else:
                    computation_ops[computation].append(op.group(1))
            called = _CALLS.search(rest)
            if called:
                calls[name] = called.group(1)
            for operand in set(re.findall(r"%([^\s,()=]+)", rest.split(" metadata=")[0])):
                users[operand].append(name)
        for name, (op, control) in names.items():
            if not op and name in calls and computation_ops.get(calls[name]):
                op = computation_ops[calls[name]][0]
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


_ANNOTATION = {key: re.compile(rf"{key}=([^,#]+)") for key in ("hlo_op", "hlo_module", "program_id")}


def event_op(stats: dict) -> tuple:
    """``(module name, program id, HLO instruction)`` of one profiled event, each ``None``
    where the event does not say.

    On a CPU the events carry ``hlo_op``, ``hlo_module`` and ``program_id`` stats.  On a
    GPU (JAX 0.11.2, an H200) the device's kernels and copies carry the same stats, from
    the annotations that XLA's runtime had open at the launch: no ``hlo_module`` or
    ``program_id`` where the trace began inside the program.  A collector that leaves
    those annotations as one ``kernel_annotation`` string, such as
    ``XlaModule:#prefix=...,hlo_module=jit_chunk,program_id=12#::Thunk:#name=...,hlo_op=loop_fusion.3#``
    (``xla/backends/gpu/runtime/annotation.cc``), is read too: the innermost instruction.
    """
    if "hlo_op" in stats:
        program = stats.get("program_id")
        return stats.get("hlo_module"), None if program is None else int(program), str(stats["hlo_op"])
    text = stats.get("kernel_annotation")
    if not isinstance(text, str) or "hlo_op=" not in text:
        return None, None, None
    found = {key: pattern.findall(text) for key, pattern in _ANNOTATION.items()}
    module = found["hlo_module"][-1] if found["hlo_module"] else None
    program = int(found["program_id"][-1]) if found["program_id"] else None
    return module, program, found["hlo_op"][-1]


def _on_device() -> bool:
    import jax

    return jax.default_backend() != "cpu"


def _kernel_name(instruction: str) -> str:
    """The name XLA:GPU gives the kernel it emits for an instruction (``.`` and ``-`` made
    ``_``: ``input_reduce_fusion.2`` runs as ``input_reduce_fusion_2``)."""
    return re.sub(r"[^0-9A-Za-z_]", "_", instruction)


def split_profile(trace_dir: str, index: dict, programs: set[int] | None = None) -> dict:
    """Exclusive time (ns) per part, summed over threads, of the XLA operations in the
    profile under ``trace_dir`` (only those of the programs in ``programs`` where given).

    On an accelerator the device's own kernels and copies are read.  Those that XLA:GPU
    runs inside a command buffer (a CUDA graph) carry the buffer's name
    (``command_buffer_57``), not their instruction's: the kernel's own name gives the
    instruction (:func:`_kernel_name`; a kernel that XLA reuses for an identical fusion
    elsewhere counts under the first).  Events that name no program (a trace that began
    while a program ran) are given the one among ``programs`` (else all in ``index``)
    whose instructions account for the most of them.

    Returns ``{"ns": {part: ns}, "unmatched_ns": ns of operations with no HLO found,
    "per_op_ns": Counter((program id, instruction) -> ns), "program": the program voted
    for where one was, else None}``.

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
    device = _on_device()
    first_program = {}
    for program, op in sorted(index):
        first_program.setdefault((index[(program, op)][0], op), program)
    scopes = parts()  # each instruction's part, once (not once per event)
    part_at = {key: CONTROL if control else part_of(name, scopes)
               for key, (_, name, control) in index.items()}
    lines_events = []  # per line: [start, end, program or None, instruction, kernel name]
    for plane in data.planes:
        if plane.name.startswith("/device:") != device:
            continue
        lines = list(plane.lines)
        if device and any(line.name.startswith("Stream") for line in lines):
            # the streams' kernels and copies, not the lines derived from them
            # ("XLA Ops", "XLA Modules", ... where a post-processing wrote them)
            lines = [line for line in lines if line.name.startswith("Stream")]
        for line in lines:
            events = []
            for ev in line.events:
                with warnings.catch_warnings():  # jaxlib's event_stats type, on iteration
                    warnings.simplefilter("ignore", DeprecationWarning)
                    stats = dict(ev.stats)
                module, program, op = event_op(stats)
                if device and op is not None and op.startswith("command_buffer"):
                    op = None  # the kernel's own name says more (below)
                if op is None and not device:
                    continue
                if program is None and module is not None and op is not None:
                    program = first_program.get((module, op))  # the first of its module's name
                events.append([ev.start_ns, ev.start_ns + ev.duration_ns, program, op, ev.name])
            lines_events.append(events)
    voted = None
    if device:
        kernels = collections.defaultdict(dict)  # program -> kernel name -> instruction
        for program, op in index:
            kernels[program].setdefault(_kernel_name(op), op)

        def resolve(program, op, kernel):
            if op is not None and (program, op) in index:
                return op
            return kernels[program].get(_kernel_name(kernel), op or kernel)

        unknown = collections.Counter((op, kernel) for events in lines_events
                                      for _, _, program, op, kernel in events if program is None)
        if unknown:
            candidates = programs if programs else {program for program, _ in index}
            score = {p: sum(n for (op, kernel), n in unknown.items() if (p, resolve(p, op, kernel)) in index)
                     for p in candidates}
            voted = max(sorted(score), key=score.get) if score else -1
        for events in lines_events:
            for ev in events:
                if ev[2] is None:
                    ev[2] = voted
                ev[3] = resolve(ev[2], ev[3], ev[4])
    totals = collections.Counter()
    per_op = collections.Counter()
    for events in lines_events:
        events = [(a, b, program, op) for a, b, program, op, _ in events
                  if program is not None and op is not None
                  and (programs is None or program in programs)]
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
    return {"ns": dict(totals), "unmatched_ns": unmatched, "per_op_ns": per_op, "program": voted}


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
    every event in memory until it stops (about 1 kB each: gigabytes for a chunk of many
    chains that lasts a minute), so a profile lasts at most ``max_seconds`` (``None``:
    no limit).  A chunk expected to last longer (``expected_s``, the timed chunks' length)
    is profiled in a window of ``max_seconds`` that opens a third of the way in, past the
    chains' chunk-start cache builds, so that the window holds steps only; a timer thread
    opens and closes it while the chunk runs.  ``split(n_steps, steps_per_s)`` reads the
    trace and the HLO dumped so far, keeps the step's programs (:func:`step_programs`) and
    returns :func:`per_step`'s figures over ``n_steps`` (all chains' steps of the chunk)
    where the whole chunk was profiled, else over the steps that ``steps_per_s`` (all
    chains' rate over the chunk, builds included: at the configs' chunk length the builds
    are a few percent of a chunk) gives for the window (``"window_s"``, ``"steps_estimated"`` in the
    result).  On an accelerator the whole chunk is profiled whatever its length, and
    :func:`split_profile` looks for its kernels in the programs compiled since the profiler
    was made (the chunk's own, where it compiled for this profiler's row): a trace stopped
    while the device runs can leave its CUDA context broken (seen on an H200:
    ``CUDA_ERROR_LAUNCH_FAILED`` at the next synchronisation, as in jax-ml/jax#40260), and
    it is started and stopped only while the device is idle (before the chunk's launch,
    after its results are on the host).  ``close()`` removes the trace (the dump stays for
    the next profile; :func:`remove` deletes a folder).
    """

    def __init__(self, dump_dir: str, max_seconds: float | None = 1.0, on_begin=None):
        self.dump_dir = dump_dir
        self.max_seconds = max_seconds
        self.on_begin = on_begin  # called as the profile opens
        self.trace_dir = None
        self.running = False
        self.window = False  # a window of the chunk, not the whole of it
        self.window_s = None
        self._lock = threading.Lock()
        self._timers = []
        self._t0 = None
        self._closed = False
        self._dumped_before = set(_dumped(dump_dir))  # program ids compiled before this row

    def start(self, expected_s: float | None = None) -> None:
        self.trace_dir = tempfile.mkdtemp(prefix="bayesreg-trace-")
        if self.max_seconds is None or _on_device():
            self._begin()  # the whole chunk (on an accelerator: never while the device runs)
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
        """Per-step figures of the profile (:func:`per_step`), with the window's length and
        ``busy``: seconds of operations per second of the window (on a CPU the mean number
        of busy threads; on a GPU the share of the time a kernel or copy runs).

        Raises
        ------
        RuntimeError
            Nothing was profiled (the chunk ended before its window opened), or the profile
            holds no operation of the step's programs.
        """
        if self.window_s is None:
            raise RuntimeError("the chunk ended before its profile window opened")
        index = hlo_index(self.dump_dir)
        programs = step_programs(index)
        if _on_device():  # the programs compiled since this profiler was made: the chunk's own
            programs = (set(_dumped(self.dump_dir)) - self._dumped_before) & programs or programs
        prof = split_profile(self.trace_dir, index, programs or None)
        busy_s = sum(prof["ns"].values()) / 1e9
        if not busy_s:
            raise RuntimeError("the profile holds no operation of the step's programs "
                               f"({'device' if _on_device() else 'host'} planes read)")
        steps = steps_per_s * self.window_s if self.window else n_steps
        return {**per_step(prof, steps), "window_s": self.window_s, "steps_estimated": self.window,
                "steps_profiled": steps, "busy": busy_s / self.window_s}

    def close(self, keep: str | os.PathLike | None = None) -> None:
        """End the profile and remove its trace, or move it to ``keep`` (a folder that
        TensorBoard's profile plugin or Perfetto, via ``xprof``, opens)."""
        self.stop()
        if self.trace_dir:
            if keep is not None and self.window_s is not None:
                remove(keep)
                Path(keep).parent.mkdir(parents=True, exist_ok=True)
                shutil.move(self.trace_dir, keep)
            remove(self.trace_dir)
            self.trace_dir = None


def keep_hlo(dump_dir: str, folder: str | os.PathLike) -> int:
    """Copy the after-optimisation HLO of the programs that hold a part of the step
    (:func:`step_programs`) from ``dump_dir`` into ``folder``; returns how many."""
    programs = step_programs(hlo_index(dump_dir))
    Path(folder).mkdir(parents=True, exist_ok=True)
    kept = [path for program, path in _dumped(dump_dir).items() if program in programs]
    for path in kept:
        shutil.copy(path, folder)
    return len(kept)


def remove(folder: str | None) -> None:
    if folder:
        shutil.rmtree(folder, ignore_errors=True)

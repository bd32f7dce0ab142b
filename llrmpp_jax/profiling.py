"""Where a jitted program spends its time: ``jax.profiler`` per-op durations, grouped by
the ``jax.named_scope`` each op was traced under.

The library marks its phases with named scopes (:data:`PHASES`: the splatter's projection,
binning, sort and composite, the decoder, the loss). :func:`profile_program` compiles a
function once (timed), runs it, then runs it ``repeats`` times under
``jax.profiler.trace`` and reads the trace back (``ProfileData``): every executed op
(an HLO instruction: a fusion, a dot, a sort, ...) is mapped to the ``op_name`` metadata of
its instruction in the compiled module and so to the first phase whose scope that name
contains. Backward ops keep their forward scope under ``transpose(jvp(...))``, so they are
split into ``"<phase> (backward)"``. The table is compact (JSON-ready): per phase and
per op, milliseconds per call; raw traces are deleted.

Durations are of ops as the runtime reports them: on a multi-threaded CPU two ops may run
at once, so the per-phase sums can exceed the wall time (``wall_ms`` is measured apart).
"""

from __future__ import annotations

import collections
import glob
import re
import tempfile
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass

import jax

# (scope marker, phase) in priority order: an op belongs to the first scope in its name.
PHASES: tuple[tuple[str, str], ...] = (
    ("splat_sort", "splat sort"),
    ("splat_bin", "splat binning"),
    ("splat_project", "splat projection"),
    ("splat_composite", "splat composite"),
    ("decoder", "decoder"),
    ("loss", "loss"),
    ("backbone", "backbone"),
    ("gaussian_head", "gaussian head"),
)

_OP_NAME = re.compile(r'^\s*(?:ROOT\s+)?%?([\w.\-]+)\s*=.*?op_name="([^"]*)"')


@dataclass(frozen=True)
class OpRow:
    """One executed op: its HLO name, phase, milliseconds per call of the program, and
    how many times it ran per call."""

    name: str
    phase: str
    ms: float
    count: float


@dataclass(frozen=True)
class ProgramProfile:
    """:func:`profile_program`'s result."""

    compile_s: float  # lowering + XLA compile
    wall_ms: float  # median synced wall time of one call
    phases_ms: dict[str, float]  # summed op time per phase, per call
    ops: list[OpRow]  # the top ops by time

    def to_json(self) -> dict:
        return {
            "compile_s": self.compile_s,
            "wall_ms": self.wall_ms,
            "phases_ms": self.phases_ms,
            "ops": [asdict(o) for o in self.ops],
        }


def phase_of(op_name: str) -> str:
    """The phase of an op from its ``op_name`` metadata (:data:`PHASES`), ``"other"`` when
    no scope matches; ``" (backward)"`` appended for ops of a transposed (backward) pass."""
    for marker, phase in PHASES:
        if marker in op_name:
            return phase + (" (backward)" if "transpose(" in op_name else "")
    return "other" + (" (backward)" if "transpose(" in op_name else "")


def _instruction_phases(hlo_text: str) -> dict[str, str]:
    """HLO instruction name -> phase, from every instruction's ``op_name`` metadata; a
    fusion's own line names the op it was fused around."""
    out: dict[str, str] = {}
    for line in hlo_text.splitlines():
        m = _OP_NAME.match(line)
        if m:
            out.setdefault(m.group(1), phase_of(m.group(2)))
    return out


def profile_program(fn: Callable, args: tuple, repeats: int = 3, top: int = 30) -> ProgramProfile:
    """Compile ``jax.jit(fn)`` for ``args`` (timed), then profile ``repeats`` calls.

    Returns per-phase and top-``top`` per-op milliseconds per call, the compile time and
    the median wall time of a call. Runs on any backend; the trace is written to a
    temporary folder and deleted.
    """
    t0 = time.perf_counter()
    compiled = jax.jit(fn).lower(*args).compile()
    compile_s = time.perf_counter() - t0
    phases = _instruction_phases(compiled.as_text())  # pyright: ignore[reportArgumentType] -- as_text() is None only without an HLO module; a compiled program has one
    jax.block_until_ready(compiled(*args))
    walls = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(compiled(*args))
        walls.append(time.perf_counter() - t0)
    with tempfile.TemporaryDirectory() as tmp:
        jax.profiler.start_trace(tmp)
        for _ in range(repeats):
            jax.block_until_ready(compiled(*args))
        jax.profiler.stop_trace()
        paths = sorted(glob.glob(f"{tmp}/**/*.xplane.pb", recursive=True))
        data = jax.profiler.ProfileData.from_file(paths[-1])
        total: collections.Counter = collections.Counter()
        count: collections.Counter = collections.Counter()
        for plane in data.planes:
            for line in plane.lines:
                # Events nest on a line: a control-flow op (while, conditional, call) spans
                # the ops of its body, which are counted themselves, so only innermost
                # events count (else a loop's time counts twice).
                evs = sorted((ev for ev in line.events if ev.name in phases), key=lambda ev: ev.start_ns)
                for ev, nxt in zip(evs, evs[1:] + [None]):
                    if nxt is None or nxt.start_ns >= ev.end_ns:
                        total[ev.name] += ev.duration_ns
                        count[ev.name] += 1
    per_phase: collections.Counter = collections.Counter()
    for name, ns in total.items():
        per_phase[phases[name]] += ns / 1e6 / repeats  # pyright: ignore[reportArgumentType] -- a Counter of milliseconds: floats
    ops = [OpRow(name, phases[name], ns / 1e6 / repeats, count[name] / repeats) for name, ns in total.most_common(top)]
    walls.sort()
    return ProgramProfile(
        compile_s, 1e3 * walls[len(walls) // 2], {k: round(v, 3) for k, v in per_phase.most_common()}, ops
    )

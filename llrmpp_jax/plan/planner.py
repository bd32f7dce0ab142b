"""Compiling (program, target) pairs and reporting each as a row; :func:`plan` is the
``llrmpp plan`` command's library function (the rows' fields: :mod:`llrmpp_jax.plan`)."""

from __future__ import annotations

import contextlib
import functools
import re
import time
from collections.abc import Callable, Sequence

import numpy as np

from llrmpp_jax.plan.catalog import GROUPS, PROGRAM_NAMES
from llrmpp_jax.plan.hlo_cost import Chip, estimate_hlo
from llrmpp_jax.plan.programs import Program, program
from llrmpp_jax.plan.targets import TARGETS, Target, check_compiler, compile_devices, target

__all__ = [
    "GROUPS",
    "PROGRAM_NAMES",
    "TARGETS",
    "Program",
    "chip_model",
    "compile_row",
    "plan",
    "resolve_programs",
    "summary_line",
    "write_rows",
]

# libtpu: "... the total memory required for HLO temporaries (20.00G) exceeds available HBM (15.75G)."
_NEEDS = re.compile(r"\(([0-9.]+)([KMGT])i?B?\)\s*exceeds available HBM\s*\(([0-9.]+)([KMGT])i?B?\)", re.I)
_UNIT = {"K": 2**10, "M": 2**20, "G": 2**30, "T": 2**40}


def resolve_programs(names: Sequence[str]) -> list[str]:
    """Program names with the groups (``paper``, ``tiny``) expanded; one-line ``UserError`` for an unknown one."""
    out: list[str] = []
    for n in names:
        for p in GROUPS.get(n, [n]):
            if p not in PROGRAM_NAMES:
                program(p)  # raises the one-line error listing the known programs
            if p not in out:
                out.append(p)
    return out


def _cost_of(compiled) -> tuple[float | None, float | None]:
    ca = compiled.cost_analysis() or {}
    if isinstance(ca, list):
        ca = ca[0] if ca else {}
    get = lambda k: float(ca[k]) if k in ca else None  # noqa: E731
    return get("flops"), get("optimal_seconds")


@functools.cache
def chip_model(name: str) -> Chip:
    """The :class:`~llrmpp_jax.plan.hlo_cost.Chip` of target ``name``: its data-sheet rates and
    the seconds per gathered and per scatter-added index row, measured once with the chip's own
    cost model (libtpu's ``optimal_seconds`` of a 2^20-row gather and scatter-add of 32 float32
    channels, the splatter's feature rows)."""
    import jax
    import jax.numpy as jnp
    from jax.sharding import Mesh, NamedSharding, PartitionSpec

    t = target(name)
    mesh = Mesh(np.asarray(compile_devices(t)[:1]), ("batch",))
    sh = NamedSharding(mesh, PartitionSpec())
    n, f = 2**20, 32
    table = jax.ShapeDtypeStruct((n, f), jnp.float32, sharding=sh)
    idx = jax.ShapeDtypeStruct((n,), jnp.int32, sharding=sh)
    rates = []
    for fn in (lambda x, i: x[i], lambda x, i: jnp.zeros_like(x).at[i].add(x)):
        _, secs = _cost_of(jax.jit(fn).lower(table, idx).compile())
        rates.append(max(secs or 0.0, 0.0) / n)
    return Chip(t.peak_flops, t.hbm_bytes_per_s, t.ici_bytes_per_s, gather_row_s=rates[0], scatter_row_s=rates[1])


@contextlib.contextmanager
def _as_run():
    import jax

    with jax.enable_x64(False), jax.numpy_dtype_promotion("standard"):
        yield


def _needs_bytes(message: str) -> tuple[float | None, float | None]:
    """(bytes the program needs, bytes the chip has) from the compiler's out-of-memory message."""
    m = _NEEDS.search(message)
    if not m:
        return None, None
    return float(m.group(1)) * _UNIT[m.group(2).upper()], float(m.group(3)) * _UNIT[m.group(4).upper()]


def compile_row(prog: Program, t: Target, flops_cache: dict[str, float | None] | None = None) -> dict:
    """Compile ``prog`` for target ``t`` and return its row (see the module doc);
    ``flops_cache`` keeps the programs' model FLOPs across targets."""
    import jax
    from jax.sharding import Mesh

    from llrmpp_jax.benchmarks.measure import memory_analysis_bytes

    row: dict = {
        "program": prog.name,
        "describe": prog.describe,
        "target": t.name,
        "chips": t.chips,
        "device_kind": t.device_kind,
        "hbm_bytes": t.hbm_bytes,
        "peak_flops": t.peak_flops,
    }
    mesh = Mesh(np.asarray(compile_devices(t)), ("batch",))
    t0 = time.perf_counter()
    try:
        # As the programs run: TPUs have no 64-bit integers (XLA emulates them, loop counters
        # included), the model's programs are float32/bf16 throughout, and its bf16 programs
        # mix bf16 parameters with float32 cameras under JAX's standard promotion.
        with _as_run():
            fn, args = prog.build(mesh, t.platform)
            compiled = fn.lower(*args).compile()
    except Exception as e:  # noqa: BLE001 -- the compiler's verdict is the row, not a crash
        message = " ".join(str(e).split())
        row.update(compiled=False, compile_s=time.perf_counter() - t0, error=message[:600])
        if "RESOURCE_EXHAUSTED" in message or "exceeds" in message and "memory" in message.lower():
            need, have = _needs_bytes(message)
            row.update(fits=False, needs_bytes=need, hbm_available_bytes=have)
        return row
    row["compile_s"] = time.perf_counter() - t0
    mem = memory_analysis_bytes(compiled)
    needed = mem["xla_peak_bytes"]
    row.update(
        compiled=True,
        memory=mem,
        hbm_needed_bytes=needed,
        fits=needed <= t.hbm_bytes,
        margin=1.0 - needed / t.hbm_bytes,
    )
    row["xla_flops"], row["xla_optimal_s"] = _cost_of(compiled)
    text = compiled.as_text()
    try:
        est = estimate_hlo(text, chip_model(t.name))
    except ValueError as e:  # an HLO form the reader does not know: the fit stands without an estimate
        row.update(estimate=None, estimate_error=str(e))
        est = None
    else:
        row["estimate"] = est.to_json()
    cache = {} if flops_cache is None else flops_cache
    if prog.name not in cache:
        with _as_run():
            cache[prog.name] = prog.flops(t.platform) if prog.flops else None
    flops = cache[prog.name]
    row["model_flops"] = flops
    if flops:
        row["matmul_limit_s"] = flops / t.peak_flops
        row["peak_fraction"] = row["matmul_limit_s"] / est.seconds if est is not None and est.seconds > 0 else None
    del compiled
    jax.clear_caches()
    return row


def plan(
    programs: Sequence[str],
    targets: Sequence[str],
    log: Callable[[str], None] = print,
    save: Callable[[list[dict]], None] | None = None,
) -> list[dict]:
    """One :func:`compile_row` per (program, target), programs' groups expanded; ``log`` gets a
    line per row and ``save`` the rows so far after each (a stopped run keeps what it did).
    Unknown names fail with one line before anything compiles."""
    names = resolve_programs(programs)
    chips = [target(t) for t in targets]
    check_compiler(chips)
    rows: list[dict] = []
    flops: dict[str, float | None] = {}
    for name in names:
        for t in chips:
            log(f"compiling {name} for {t.name} ...")
            row = compile_row(program(name), t, flops)
            rows.append(row)
            log(summary_line(row))
            if save:
                save(rows)
    return rows


def summary_line(row: dict) -> str:
    """One line of a row: fit, compile time, estimate."""
    gib = 2.0**30
    head = f"{row['program']} on {row['target']}: "
    if not row["compiled"]:
        need = row.get("needs_bytes")
        have = row.get("hbm_available_bytes") or row["hbm_bytes"]
        what = (
            f"does not fit: needs {need / gib:.1f} GiB of {have / gib:.2f}"
            if need
            else ("does not fit" if row.get("fits") is False else f"error: {row['error'][:200]}")
        )
        return head + f"{what} (compile {row['compile_s']:.0f} s)"
    est = row["estimate"]
    limit = row.get("matmul_limit_s")
    return head + (
        f"{row['hbm_needed_bytes'] / gib:.2f} of {row['hbm_bytes'] / gib:.0f} GiB "
        f"({'fits' if row['fits'] else 'does NOT fit'}), compiled in {row['compile_s']:.0f} s, "
        + (f"estimate {est['seconds']:.3g} s" if est else f"no estimate ({row.get('estimate_error')})")
        + (f", matmul limit {limit:.3g} s" if limit else "")
    )


def write_rows(rows: list[dict], path: str) -> None:
    """``rows`` as JSON at ``path``, written whole or not at all (a temporary file renamed)."""
    import json
    import os

    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    tmp = f"{path}.tmp"
    with open(tmp, "w") as f:
        json.dump({"rows": rows}, f, indent=1)
    os.replace(tmp, path)

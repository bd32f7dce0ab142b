"""What the benchmarks measure with: the environment record, synced timing of a compiled
program, XLA's FLOP and byte counts, a traced matmul FLOP count, the device's peak memory,
achieved TFLOP/s against the card's dense bf16 peak (:data:`PEAK_BF16_TFLOPS`), and
Markdown tables. Used by the benchmarks in :mod:`llrmpp_jax.benchmarks` and
``llrmpp doctor``.
"""

from __future__ import annotations

import importlib.metadata
import math
import os
import platform
import time


def environment() -> dict:
    """Device, platform, library versions, matmul precision, ``XLA_FLAGS`` and the 1/5/15-min load average."""
    import jax

    versions = {}
    for pkg in ("jax", "jaxlib", "flax", "optax", "orbax-checkpoint", "numpy"):  # None: not installed
        try:
            versions[pkg] = importlib.metadata.version(pkg)
        except importlib.metadata.PackageNotFoundError:
            versions[pkg] = None
    dev = jax.devices()[0]
    return {
        "backend": jax.default_backend(),
        "device": str(dev),
        "device_kind": dev.device_kind,
        "device_count": jax.device_count(),
        "host": platform.machine(),
        "cpu_count": os.cpu_count(),
        "versions": versions,
        "default_matmul_precision": jax.config.jax_default_matmul_precision or "default (backend's own)",  # pyright: ignore[reportAttributeAccessIssue] -- jax.config's options are made at run time; its stub lists none
        "xla_flags": os.environ.get("XLA_FLAGS", ""),
        "load_average": list(os.getloadavg()),
    }


# Dense (no sparsity) bf16 tensor-core peak of the cards the project measures on, TFLOP/s,
# from the vendors' data sheets (SXM parts): H100 and H200 share the compute die.
PEAK_BF16_TFLOPS = {"H100": 989.0, "H200": 989.0, "A100": 312.0}


def peak_bf16_flops(device_kind: str) -> float | None:
    """The card's dense bf16 peak in FLOP/s from its ``device_kind`` (``"NVIDIA H100 80GB
    HBM3"`` -> 989e12), None for a device not in :data:`PEAK_BF16_TFLOPS` (a CPU)."""
    for name, tflops in PEAK_BF16_TFLOPS.items():
        if name in device_kind:
            return tflops * 1e12
    return None


def xla_cost(compiled) -> dict[str, float | None]:
    """XLA's cost analysis of a compiled program: ``flops`` and ``bytes_accessed`` (None
    where the backend reports none). A ``while`` loop's body is counted once whatever its
    trip count, and custom calls (cuDNN attention) count nothing."""
    try:
        ca = compiled.cost_analysis() or {}
    except Exception:  # noqa: BLE001 -- a backend without it must not lose the timings around it
        ca = {}
    if isinstance(ca, list):  # one entry per program on some jax versions
        ca = ca[0] if ca else {}
    get = lambda k: float(ca[k]) if k in ca else None  # noqa: E731
    return {"flops": get("flops"), "bytes_accessed": get("bytes accessed")}


def memory_analysis_bytes(compiled) -> dict[str, int]:
    """XLA's ``memory_analysis()`` of a compiled step: argument, output, alias and temp bytes,
    ``xla_total_bytes`` (their sum without alias) and ``xla_peak_bytes`` (total - alias)."""
    ma = compiled.memory_analysis()
    out = {k: int(getattr(ma, f"{k}_size_in_bytes")) for k in ("argument", "output", "alias", "temp")}
    out["xla_total_bytes"] = out["argument"] + out["output"] + out["temp"]
    out["xla_peak_bytes"] = out["xla_total_bytes"] - out["alias"]
    return out


def matmul_flops(fn, *args) -> float:
    """FLOPs (2 per multiply-add) of every ``dot_general`` and convolution ``fn`` traces to at
    the shapes of ``args`` (arrays or ``ShapeDtypeStruct`` s), nested programs included: a
    ``scan`` body times its length, a ``cond``'s costliest branch, a ``while`` body once.
    Tracing only, nothing compiled. The arithmetic a card's tensor-core peak is quoted for;
    elementwise work, sorts and gathers are not counted (XLA's cost analysis charges a
    long ``cumsum``, a ``reduce_window``, its window times its length)."""
    import jax

    return _jaxpr_matmul_flops(jax.make_jaxpr(fn)(*args).jaxpr)


def _conv_flops(eqn) -> float:
    """2 x the multiply-adds of one ``conv_general_dilated`` that touch no padding: per
    spatial axis the (output position, kernel tap) pairs landing on an input element
    (strides and dilations included), times batch, output and per-group input features.
    A gradient's transposed convolution thus counts as its forward does, as XLA counts it."""
    import numpy as np

    p = eqn.params
    dn = p["dimension_numbers"]
    lhs, rhs, out = (v.aval.shape for v in (*eqn.invars[:2], eqn.outvars[0]))
    pairs = 1
    for ax, (lo, _) in enumerate(p["padding"]):
        n_in, n_k, n_out = lhs[dn.lhs_spec[2 + ax]], rhs[dn.rhs_spec[2 + ax]], out[dn.out_spec[2 + ax]]
        pos = np.arange(n_out)[:, None] * p["window_strides"][ax] + np.arange(n_k)[None, :] * p["rhs_dilation"][ax] - lo
        dil = p["lhs_dilation"][ax]
        pairs *= int(np.sum((pos >= 0) & (pos <= (n_in - 1) * dil) & (pos % dil == 0)))
    batch = lhs[dn.lhs_spec[0]] // p["batch_group_count"]
    return 2.0 * batch * out[dn.out_spec[1]] * rhs[dn.rhs_spec[1]] * pairs


def _jaxpr_matmul_flops(jaxpr) -> float:
    from jax.extend import core

    def sub(v) -> list:  # the jaxprs held by an equation's parameter
        if isinstance(v, core.ClosedJaxpr):
            return [v.jaxpr]
        if isinstance(v, core.Jaxpr):
            return [v]
        if isinstance(v, (tuple, list)):
            return [j for x in v for j in sub(x)]
        return []

    total = 0.0
    for eqn in jaxpr.eqns:
        name = eqn.primitive.name
        if name == "dot_general":
            (contract, _), _ = eqn.params["dimension_numbers"]
            lhs, out = eqn.invars[0].aval.shape, eqn.outvars[0].aval.shape
            total += 2.0 * math.prod(out) * math.prod(lhs[d] for d in contract)
        elif name == "conv_general_dilated":
            total += _conv_flops(eqn)
        elif name == "scan":
            total += eqn.params["length"] * _jaxpr_matmul_flops(eqn.params["jaxpr"].jaxpr)
        elif name == "cond":
            total += max(_jaxpr_matmul_flops(b.jaxpr) for b in eqn.params["branches"])
        else:  # pjit, remat, custom_jvp/vjp calls, while, shard_map: their bodies once
            total += sum(_jaxpr_matmul_flops(j) for v in eqn.params.values() for j in sub(v))
    return total


def device_peak_bytes() -> int | None:
    """The first device's ``peak_bytes_in_use`` (the process's peak so far; None where the
    backend keeps no statistics, as on CPU)."""
    import jax

    return (jax.devices()[0].memory_stats() or {}).get("peak_bytes_in_use")


def throughput(flops: float | None, seconds: float, device_kind: str) -> dict[str, float | None]:
    """``tflops_per_s`` (``flops / seconds / 1e12``) and ``peak_fraction`` (of the card's
    dense bf16 peak, :func:`peak_bf16_flops`); None where ``flops`` or the peak is unknown."""
    if flops is None:
        return {"tflops_per_s": None, "peak_fraction": None}
    peak = peak_bf16_flops(device_kind)
    return {"tflops_per_s": flops / seconds / 1e12, "peak_fraction": None if peak is None else flops / seconds / peak}


def timed_with_output(fn, *args, repeats: int = 3, warmup: int = 1) -> tuple[dict, object]:
    """:func:`timed`, and the last call's output."""
    import jax

    t0 = time.perf_counter()
    compiled = jax.jit(fn).lower(*args).compile()
    compile_s = time.perf_counter() - t0
    out = None
    for _ in range(warmup):
        out = jax.block_until_ready(compiled(*args))
    runs = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = jax.block_until_ready(compiled(*args))
        runs.append(time.perf_counter() - t0)
    ordered = sorted(runs)
    cost = xla_cost(compiled)
    return {
        "compile_s": compile_s,
        "run_s_median": ordered[len(ordered) // 2],
        "run_s_min": ordered[0],
        "run_s_all": runs,
        "temp_bytes": int(compiled.memory_analysis().temp_size_in_bytes),  # pyright: ignore[reportOptionalMemberAccess] -- memory_analysis() is None only on a backend without it; CPU, GPU and TPU have it
        "xla_flops": cost["flops"],
        "xla_bytes_accessed": cost["bytes_accessed"],
        "device_peak_bytes": device_peak_bytes(),
    }, out


def timed(fn, *args, repeats: int = 3, warmup: int = 1) -> dict:
    """Compile ``jit(fn)`` for ``args`` and time ``repeats`` synced calls after ``warmup`` untimed ones.

    Returns ``compile_s`` (lower + compile), ``run_s_median`` / ``run_s_min`` / ``run_s_all``
    (seconds per call, ``block_until_ready``), XLA's ``temp_bytes`` and cost analysis of the
    compiled program (``xla_flops``, ``xla_bytes_accessed``: :func:`xla_cost`) and the
    device's ``device_peak_bytes`` after the calls (:func:`device_peak_bytes`).
    """
    return timed_with_output(fn, *args, repeats=repeats, warmup=warmup)[0]


def markdown_table(header: tuple[str, ...], rows: list[tuple]) -> str:
    """A GitHub Markdown table of ``rows`` (each as many cells as ``header``, printed with ``str``)."""
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(str(c) for c in row) + " |" for row in rows]
    return "\n".join(lines)

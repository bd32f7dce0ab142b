"""A time estimate of a compiled XLA program from its optimised HLO text: per-op rooflines,
every ``while`` body counted as many times as its loop runs.

XLA's own ``cost_analysis()`` counts a ``while`` body once whatever its trip count (every
``lax.scan``, so the remat loops over the backbone's blocks and the SSD's chunk recurrence),
and on TPU its ``optimal_seconds`` comes out negative once the module holds a custom call.
This module reads the scheduled HLO module (``compiled.as_text()``) instead:

* **ops**: each instruction of a computation, after fusion, costs
  ``max(flops / peak_flops, bytes / hbm_bytes_per_s)``: ``flops`` are the matrix products'
  (``dot`` and ``convolution``, inside a fusion too; 2 per multiply-add), ``bytes`` the
  sizes of the instruction's operands and result, except arrays placed in on-chip memory
  (a TPU layout's ``S(1)``, VMEM), which move no HBM bytes. Elementwise arithmetic is taken
  as free beside its memory traffic (the vector units are not modelled).
* **gathers and scatters** (alone or fused) are priced per index row at ``row_seconds``,
  a rate the caller measures with the chip's own cost model (:func:`llrmpp_jax.plan.targets`
  calibrates it): TPUs move gathered rows one by one, far below the HBM roofline.
* **control flow**: a ``while`` costs its trip count times its body and condition, the trip
  count read from the condition (``counter < constant``, as ``lax.scan`` and
  ``lax.fori_loop`` lower) or from ``known_trip_count``; a loop whose count the HLO does not
  state (a ``lax.while_loop`` with a data-dependent stop) is counted ``unknown_trip_count``
  times and listed in ``unknown_loops``. A ``conditional`` costs its dearest branch; ``call``
  and async wrappers their callee.
* **custom calls** (cuDNN, Pallas kernels) cost their memory traffic, or, where the call's
  backend config carries a cost estimate (a Pallas ``pl.CostEstimate``), its flops and bytes.
  The Pallas splash-attention kernels carry none; they are given their matrix products from
  their q and k operands ``[heads, L, hd]``: ``c x heads x Lq x Lk x hd`` FLOPs with c = 4
  (forward: q k^T and p v), 6 (dq: logits, dp, dq) and 8 (dkv: logits, dv, dp, dk), over the
  padded lengths the kernel runs.
* **collectives** (all-reduce, all-gather, reduce-scatter, collective-permute, all-to-all)
  cost ``2 x bytes / ici_bytes_per_s`` (a ring's send and receive).

The sum is a lower bound of the kind MaxText's and XLA's cost models give: it assumes every
op runs at the better of its two limits and that nothing overlaps badly.
"""

from __future__ import annotations

import json
import math
import re
from dataclasses import dataclass, field

import numpy as np

DTYPE_BYTES = {
    "pred": 1,
    "s8": 1,
    "u8": 1,
    "s16": 2,
    "u16": 2,
    "s32": 4,
    "u32": 4,
    "s64": 8,
    "u64": 8,
    "bf16": 2,
    "f16": 2,
    "f32": 4,
    "f64": 8,
    "c64": 8,
    "c128": 16,
    "s4": 0.5,
    "u4": 0.5,
    "f8e4m3fn": 1,
    "f8e5m2": 1,
    "f8e4m3b11fnuz": 1,
    "f8e4m3fnuz": 1,
    "f8e5m2fnuz": 1,
    "token": 0,
}
_ARRAY = re.compile(r"([a-z][a-z0-9]*)\[([0-9,]*)\](\{[^}]*\})?")
_INSTR = re.compile(r"^\s*(?:ROOT\s+)?%([^\s=]+)\s*=\s*(.*)$")
_HEADER = re.compile(r"^(ENTRY\s+)?%([^\s(]+)\s*\(")
_CALLS = re.compile(r"(?:calls|to_apply|body|condition)=%([^\s,)}]+)")
_CLOSE = re.compile(r'^\}(\s*,\s*execution_thread="[^"]*")?\s*$')
_BRANCHES = re.compile(r"branch_computations=\{([^}]*)\}")
# Pallas splash-attention kernels by name, and their matmul FLOPs per (head, query, key, hd).
_SPLASH = re.compile(r"^splash_m[hq]a_(fwd|dq|dkv)")
_SPLASH_FLOPS = {"fwd": 4, "dq": 6, "dkv": 8}
_COLLECTIVES = ("all-reduce", "all-gather", "reduce-scatter", "collective-permute", "all-to-all")
_FREE = {
    "parameter",
    "constant",
    "get-tuple-element",
    "tuple",
    "bitcast",
    "after-all",
    "partition-id",
    "replica-id",
    "iota",
    "opt-barrier",
    "add-dependency",
}


@dataclass
class Instr:
    """One HLO instruction: ``name``, result ``shape`` text, ``opcode``, operand names, the
    text inside its parentheses (a constant's value), attributes text."""

    name: str
    shape: str
    opcode: str
    operands: list[str]
    args: str
    attrs: str


@dataclass
class Chip:
    """What the estimate needs of a chip: dense bf16 matrix FLOP/s, HBM bytes/s, interconnect
    bytes/s per chip, seconds per gathered or scattered index row."""

    peak_flops: float
    hbm_bytes_per_s: float
    ici_bytes_per_s: float
    gather_row_s: float = 0.0
    scatter_row_s: float = 0.0


@dataclass
class Estimate:
    """``seconds`` (the sum), its parts (``matmul_s``: ops bound by their FLOPs, ``memory_s``:
    by their bytes, ``gather_s``, ``collective_s``, ``custom_call_s``), the FLOPs and HBM bytes
    counted with loop trip counts, and the loops whose trip count was not stated."""

    seconds: float = 0.0
    matmul_s: float = 0.0
    memory_s: float = 0.0
    gather_s: float = 0.0
    collective_s: float = 0.0
    custom_call_s: float = 0.0
    flops: float = 0.0
    bytes: float = 0.0
    loops: int = 0
    unknown_loops: list[str] = field(default_factory=list)

    def add(self, other: Estimate, times: float = 1.0) -> None:
        for k in ("seconds", "matmul_s", "memory_s", "gather_s", "collective_s", "custom_call_s", "flops", "bytes"):
            setattr(self, k, getattr(self, k) + times * getattr(other, k))
        self.loops += other.loops
        self.unknown_loops += [u for u in other.unknown_loops if u not in self.unknown_loops]

    def to_json(self) -> dict:
        return {
            k: getattr(self, k)
            for k in (
                "seconds",
                "matmul_s",
                "memory_s",
                "gather_s",
                "collective_s",
                "custom_call_s",
                "flops",
                "bytes",
                "loops",
                "unknown_loops",
            )
        }


def _split_shape(rest: str) -> tuple[str, str]:
    """``"(a, b) op(...)..."`` or ``"f32[2]{0} op(...)"`` -> (shape text, the rest)."""
    if rest.startswith("("):
        depth = 0
        for i, ch in enumerate(rest):
            depth += ch == "("
            depth -= ch == ")"
            if depth == 0:
                return rest[: i + 1], rest[i + 1 :].lstrip()
    shape, _, tail = rest.partition(" ")
    return shape, tail


def _parse_instr(line: str) -> Instr | None:
    m = _INSTR.match(line)
    if not m:
        return None
    name, rest = m.groups()
    shape, tail = _split_shape(rest)
    paren = tail.find("(")
    if paren < 0:
        return None
    opcode = tail[:paren].strip()
    depth, end = 0, len(tail)
    for i in range(paren, len(tail)):
        depth += tail[i] == "("
        depth -= tail[i] == ")"
        if depth == 0:
            end = i
            break
    args = tail[paren + 1 : end]
    return Instr(name, shape, opcode, re.findall(r"%([^\s,)]+)", args), args, tail[end + 1 :])


def parse_module(text: str) -> tuple[dict[str, list[Instr]], str]:
    """HLO module text -> ({computation name: instructions}, entry computation's name)."""
    comps: dict[str, list[Instr]] = {}
    entry, current = "", None
    for line in text.splitlines():
        if current is None:
            m = _HEADER.match(line)
            if m and line.rstrip().endswith("{"):
                current = m.group(2)
                comps[current] = []
                entry = current if m.group(1) else entry
            continue
        if _CLOSE.match(line):  # "}" or, on TPU, '}, execution_thread="sparsecore"'
            current = None
            continue
        ins = _parse_instr(line)
        if ins is not None:
            comps[current].append(ins)
        elif comps[current]:
            # An instruction's attributes may span lines (a Pallas kernel's metadata holds
            # newlines, and a continuation line can start with "}}"): they stay its own.
            comps[current][-1].attrs += "\n" + line
    if not entry:
        raise ValueError("HLO text has no ENTRY computation")
    return comps, entry


def _arrays(shape: str) -> list[tuple[str, tuple[int, ...], str]]:
    return [(d, tuple(int(x) for x in dims.split(",") if x), lay or "") for d, dims, lay in _ARRAY.findall(shape)]


def hbm_bytes(shape: str) -> float:
    """Bytes of the arrays in ``shape`` that live in HBM (memory space ``S(1)``, on-chip, excluded)."""
    return sum(DTYPE_BYTES.get(d, 4) * math.prod(dims) for d, dims, lay in _arrays(shape) if "S(1)" not in lay)


def _dims(shape: str) -> tuple[int, ...]:
    arrays = _arrays(shape)
    return arrays[0][1] if arrays else ()


def _matmul_flops(ins: Instr, shapes: dict[str, str]) -> float:
    """2 x multiply-adds of a ``dot`` or ``convolution`` (0 for anything else)."""
    out = _dims(ins.shape)
    if ins.opcode == "dot":
        m = re.search(r"lhs_contracting_dims=\{([0-9,]*)\}", ins.attrs)
        lhs = _dims(shapes.get(ins.operands[0], ""))
        k = math.prod(lhs[int(i)] for i in m.group(1).split(",") if i) if m and lhs else 1
        return 2.0 * math.prod(out) * k
    if ins.opcode == "convolution" and len(ins.operands) > 1:
        return _conv_flops(ins, _dims(shapes.get(ins.operands[0], "")), _dims(shapes.get(ins.operands[1], "")), out)
    return 0.0


def _splash_flops(ins: Instr, shapes: dict[str, str]) -> float:
    """Matrix-product FLOPs of a splash-attention kernel (module docstring); 0 for any other call."""
    m = _SPLASH.match(ins.name)
    if not m or len(ins.operands) < 4:
        return 0.0
    q, k = (_dims(shapes.get(o, "")) for o in ins.operands[2:4])  # after the two prefetched mask arrays
    if len(q) != 3 or len(k) != 3:
        return 0.0
    return float(_SPLASH_FLOPS[m.group(1)] * q[0] * q[1] * k[1] * q[2])


def _window(attrs: str, key: str, n: int, default: int) -> list[int]:
    m = re.search(rf"\b{key}=([0-9x_-]+)", attrs)
    return [int(v) for v in m.group(1).split("x")] if m else [default] * n


def _conv_flops(ins: Instr, lhs: tuple[int, ...], rhs: tuple[int, ...], out: tuple[int, ...]) -> float:
    """2 x the multiply-adds of an HLO ``convolution`` that touch no padding or dilation hole:
    per spatial axis the (output position, window tap) pairs that land on an input element.
    TPU's compiler writes batched matrix products as convolutions whose batch axes are
    spatial axes with ``lhs_dilate`` = window = the batch size, so each output position meets
    one real input element there; counting taps on real elements gets their FLOPs right."""
    m = re.search(r"dim_labels=([0-9a-z]+)_([0-9a-z]+)->([0-9a-z]+)", ins.attrs)
    if not m or not lhs or not rhs or not out:
        return 0.0
    ll, rl, ol = m.groups()
    spatial = sorted(c for c in ll if c.isdigit())
    n = len(spatial)
    size = _window(ins.attrs, "size", n, 0)
    stride, lhs_dil, rhs_dil = (_window(ins.attrs, k, n, 1) for k in ("stride", "lhs_dilate", "rhs_dilate"))
    pm = re.search(r"\bpad=([0-9x_-]+)", ins.attrs)
    pad_lo = [int(p.split("_")[0]) for p in pm.group(1).split("x")] if pm else [0] * n
    pairs = 1
    for ax, c in enumerate(spatial):
        n_in, n_k, n_out = lhs[ll.index(c)], size[ax] or rhs[rl.index(c)], out[ol.index(c)]
        pos = np.arange(n_out)[:, None] * stride[ax] + np.arange(n_k)[None, :] * rhs_dil[ax] - pad_lo[ax]
        d = lhs_dil[ax]
        pairs *= int(np.sum((pos >= 0) & (pos <= (n_in - 1) * d) & (pos % d == 0)))
    bg = re.search(r"batch_group_count=(\d+)", ins.attrs)
    batch = lhs[ll.index("b")] // (int(bg.group(1)) if bg else 1)
    return 2.0 * batch * out[ol.index("f")] * rhs[rl.index("i")] * pairs


def _index_rows(ins: Instr, shapes: dict[str, str]) -> tuple[int, int]:
    """(gathered, scattered) index rows of one instruction: its indices' elements over the
    index vector's length."""
    if ins.opcode not in ("gather", "scatter"):
        return 0, 0
    idx = _dims(shapes.get(ins.operands[1], "")) if len(ins.operands) > 1 else ()
    m = re.search(r"index_vector_dim=(\d+)", ins.attrs)
    vec = idx[int(m.group(1))] if m and idx and int(m.group(1)) < len(idx) else 1
    rows = math.prod(idx) // max(vec, 1) if idx else 0
    return (rows, 0) if ins.opcode == "gather" else (0, rows)


def _trip_count(ins: Instr, comps: dict[str, list[Instr]]) -> int | None:
    m = re.search(r'"known_trip_count":\{"n":"(\d+)"', ins.attrs)
    if m:
        return int(m.group(1))
    cond = re.search(r"condition=%([^\s,]+)", ins.attrs)
    body = comps.get(cond.group(1), []) if cond else []
    consts = {i.name: int(i.args) for i in body if i.opcode == "constant" and re.fullmatch(r"-?\d+", i.args)}
    root = body[-1] if body else None
    if root is not None and root.opcode == "compare" and "direction=LT" in root.attrs:
        for op in root.operands:
            if op in consts:
                return consts[op]
    return None


class _Costing:
    def __init__(self, comps: dict[str, list[Instr]], chip: Chip, unknown_trip_count: int):
        self.comps, self.chip, self.unknown = comps, chip, unknown_trip_count
        self.memo: dict[str, Estimate] = {}
        self.inner: dict[str, tuple[float, int, int]] = {}
        self.reads: dict[tuple[str, int], float] = {}

    def fused(self, name: str) -> tuple[float, int, int]:
        """(matmul FLOPs, gathered rows, scattered rows) inside a fused computation, nested
        fusions included."""
        if name not in self.inner:
            body = self.comps.get(name, [])
            shapes = {i.name: i.shape for i in body}
            flops, gathered, scattered = 0.0, 0, 0
            for i in body:
                g, s = _index_rows(i, shapes)
                flops, gathered, scattered = flops + _matmul_flops(i, shapes), gathered + g, scattered + s
                if i.opcode == "fusion":
                    for callee in _CALLS.findall(i.attrs):
                        f, g, s = self.fused(callee)
                        flops, gathered, scattered = flops + f, gathered + g, scattered + s
            self.inner[name] = (flops, gathered, scattered)
        return self.inner[name]

    def param_read(self, comp: str, index: int, full: float) -> float:
        """HBM bytes fused computation ``comp`` reads of its parameter ``index`` (``full`` bytes):
        only the slices it takes where every use slices it (or hands it to a nested fusion that
        does); none where it is a buffer updated in place; else all of it."""
        key = (comp, index)
        if key not in self.reads:
            body = self.comps.get(comp, [])
            name = next((i.name for i in body if i.opcode == "parameter" and i.args == str(index)), None)
            uses = [(i, k) for i in body for k, o in enumerate(i.operands) if o == name] if name else []
            read = 0.0
            for u, k in uses:
                if u.opcode in ("dynamic-slice", "slice", "gather") and k == 0:
                    read += hbm_bytes(u.shape)
                elif u.opcode == "dynamic-update-slice" and k == 0:
                    continue
                elif u.opcode == "fusion":
                    read += self.param_read(next(iter(_CALLS.findall(u.attrs)), ""), k, full)
                else:
                    read = full
                    break
            self.reads[key] = min(read, full) if uses else full
        return self.reads[key]

    def moved_bytes(self, ins: Instr, shapes: dict[str, str]) -> float:
        """HBM bytes an op reads and writes: its operands and result, except that a slice
        of an operand (``dynamic-slice``, ``slice``, ``gather``: inside a fusion too) reads only
        what it takes and an in-place ``dynamic-update-slice`` writes only its update."""
        operands = [hbm_bytes(shapes.get(o, "")) for o in ins.operands]
        result = hbm_bytes(ins.shape)
        if ins.opcode in ("dynamic-slice", "slice", "gather"):
            return 2.0 * result + sum(operands[1:])
        if ins.opcode == "dynamic-update-slice":
            return 2.0 * (operands[1] if len(operands) > 1 else result) + sum(operands[2:])
        if ins.opcode != "fusion":
            return result + sum(operands)
        callee = next(iter(_CALLS.findall(ins.attrs)), None)
        body = self.comps.get(callee or "", [])
        total = sum(self.param_read(callee or "", k, full) for k, full in enumerate(operands))
        root = body[-1] if body else None
        by_name = {i.name: i for i in body}
        outs = [by_name.get(o) for o in root.operands] if root is not None and root.opcode == "tuple" else [root]
        for out in outs:
            if out is not None and out.opcode == "dynamic-update-slice" and len(out.operands) > 1:
                update = by_name.get(out.operands[1])
                total += hbm_bytes(update.shape) if update is not None else 0.0
            elif out is not None:
                total += hbm_bytes(out.shape)
        return total if body else result + sum(operands)

    def op(self, ins: Instr, shapes: dict[str, str]) -> Estimate:
        e = Estimate()
        code = ins.opcode
        if code in _FREE:
            return e
        nbytes = self.moved_bytes(ins, shapes)
        if code == "while":
            trips = _trip_count(ins, self.comps)
            if trips is None:
                trips = self.unknown
                e.unknown_loops.append(ins.name)
            for callee in _CALLS.findall(ins.attrs):
                e.add(self.computation(callee), trips)
            e.loops += 1
            return e
        if code == "conditional":
            m = _BRANCHES.search(ins.attrs)
            branches = re.findall(r"%([^\s,]+)", m.group(1)) if m else _CALLS.findall(ins.attrs)
            costs = [self.computation(b) for b in branches]
            if costs:
                e.add(max(costs, key=lambda c: c.seconds))
            return e
        if (
            code in ("call", "async-start", "async-done", "async-update")
            or code.endswith("-start")
            and "calls=" in ins.attrs
        ):
            for callee in _CALLS.findall(ins.attrs):
                e.add(self.computation(callee))
            return e
        base = code.removesuffix("-start").removesuffix("-done")
        if base in _COLLECTIVES:
            if not code.endswith("-done"):
                e.collective_s = 2.0 * hbm_bytes(ins.shape) / self.chip.ici_bytes_per_s
                e.seconds = e.collective_s
            return e
        flops, (gathered, scattered) = _matmul_flops(ins, shapes), _index_rows(ins, shapes)
        if code == "fusion":
            for callee in _CALLS.findall(ins.attrs):
                f, g, s = self.fused(callee)
                flops, gathered, scattered = flops + f, gathered + g, scattered + s
        if code == "custom-call":
            est = re.search(r'"cost_estimate":\s*(\{[^}]*\})', ins.attrs)
            flops = _splash_flops(ins, shapes)
            if est:
                try:
                    ce = json.loads(est.group(1))
                    flops, nbytes = float(ce.get("flops", 0)), float(ce.get("bytes_accessed", nbytes))
                except ValueError:
                    pass
        e.flops, e.bytes = flops, nbytes
        t_mm, t_mem = flops / self.chip.peak_flops, nbytes / self.chip.hbm_bytes_per_s
        t_rows = gathered * self.chip.gather_row_s + scattered * self.chip.scatter_row_s
        t = max(t_mm, t_mem, t_rows)
        e.seconds = t
        if code == "custom-call":
            e.custom_call_s = t
        elif t == t_rows and gathered + scattered:
            e.gather_s = t
        elif t == t_mm and flops:
            e.matmul_s = t
        else:
            e.memory_s = t
        return e

    def computation(self, name: str) -> Estimate:
        if name not in self.memo:
            body = self.comps.get(name, [])
            shapes = {i.name: i.shape for i in body}
            total = Estimate()
            for ins in body:
                total.add(self.op(ins, shapes))
            self.memo[name] = total
        return self.memo[name]


def estimate_hlo(text: str, chip: Chip, unknown_trip_count: int = 1) -> Estimate:
    """The :class:`Estimate` of the optimised HLO module ``text`` on ``chip``; a loop with no
    stated trip count counts ``unknown_trip_count`` times (and is named in ``unknown_loops``)."""
    comps, entry = parse_module(text)
    return _Costing(comps, chip, unknown_trip_count).computation(entry)

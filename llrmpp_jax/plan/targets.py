"""Accelerators a program can be compiled for without one: TPU chips through libtpu's
compile-only topologies, each with the figures a fit and a time estimate need.

``compile_devices(target)`` returns the target's devices as the TPU compiler sees them
(``jax.experimental.topologies.get_topology_desc``), usable in a :class:`jax.sharding.Mesh`
and in ``jax.jit(f).lower(...).compile()`` from a CPU-only machine; nothing runs on them.
Needs libtpu (``pip install 'llrmpp-jax[tpu]'``). A target of ``chips > 1`` is a data-parallel
slice: the program's batch split over that many devices, so its collectives compile too.

Chip figures are the vendors' data-sheet values per JAX device: dense bf16 matrix FLOP/s,
HBM capacity and bandwidth, and inter-chip bandwidth. On TPU7x (Ironwood) JAX shows each of
a chip's two TensorCores as one device, with half the chip's HBM and FLOP/s.
"""

from __future__ import annotations

import functools
import os
from dataclasses import dataclass

from llrmpp_jax.errors import UserError

GIB = 2.0**30
TPU_INSTALL = "pip install 'llrmpp-jax[tpu]'  (or: pip install 'jax[tpu]')"


@dataclass(frozen=True)
class Target:
    """A compile target: ``name``; libtpu's ``topology`` name (the smallest slice that holds
    ``chips`` devices); ``chips`` devices in the program's mesh; ``device_kind`` as JAX names
    it; per device: ``hbm_bytes``, ``peak_flops`` (dense bf16), ``hbm_bytes_per_s`` and
    ``ici_bytes_per_s``."""

    name: str
    topology: str
    chips: int
    device_kind: str
    hbm_bytes: float
    peak_flops: float
    hbm_bytes_per_s: float
    ici_bytes_per_s: float

    @property
    def platform(self) -> str:
        return "tpu"


def _tpu(
    name: str, topology: str, kind: str, hbm_gib: float, tflops: float, hbm_gbs: float, ici_gbs: float
) -> list[Target]:
    one = Target(name, topology, 1, kind, hbm_gib * GIB, tflops * 1e12, hbm_gbs * 1e9, ici_gbs * 1e9)
    return [
        one,
        Target(f"{name}-4", topology, 4, kind, one.hbm_bytes, one.peak_flops, one.hbm_bytes_per_s, one.ici_bytes_per_s),
    ]


# Data sheets (cloud.google.com/tpu/docs/system-architecture-tpu-vm and the per-version pages).
TARGETS: dict[str, Target] = {
    t.name: t
    for t in [
        *_tpu("v5e", "v5e:2x2", "TPU v5 lite", 16, 197, 819, 200),
        *_tpu("v5p", "v5:2x2x1", "TPU v5", 95, 459, 2765, 600),
        *_tpu("v6e", "v6e:2x2", "TPU v6 lite", 32, 918, 1640, 448),
        *_tpu("tpu7x", "tpu7x:2x2x1", "TPU7x", 96, 2307 / 2, 7370 / 2, 600),
    ]
}


def target(name: str) -> Target:
    """:data:`TARGETS` ``[name]``; one-line ``UserError`` listing the known targets otherwise."""
    if name not in TARGETS:
        raise UserError(f"plan: unknown target {name!r}; known targets: {', '.join(TARGETS)}")
    return TARGETS[name]


def check_compiler(targets: list[Target]) -> None:
    """One-line ``UserError`` with the pip command when a target's compiler is not installed."""
    import importlib.util

    if any(t.platform == "tpu" for t in targets) and importlib.util.find_spec("libtpu") is None:
        raise UserError(f"plan: compiling for TPU needs libtpu, which is not installed: {TPU_INSTALL}")


@functools.cache
def _topology(topology: str):
    check_compiler([t for t in TARGETS.values() if t.topology == topology])
    # libtpu asks the cloud metadata server for the host's TPU unless told not to: there is none.
    os.environ.setdefault("TPU_SKIP_MDS_QUERY", "1")
    os.environ.setdefault("ALLOW_MULTIPLE_LIBTPU_LOAD", "1")
    from jax.experimental import topologies

    return topologies.get_topology_desc(topology_name=topology, platform="tpu")


def compile_devices(t: Target) -> list:
    """The first ``t.chips`` compile-only devices of ``t``'s topology."""
    devices = list(_topology(t.topology).devices)
    if len(devices) < t.chips:
        raise UserError(f"plan: topology {t.topology} has {len(devices)} devices, target {t.name} needs {t.chips}")
    return devices[: t.chips]

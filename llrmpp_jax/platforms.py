"""Which JAX platforms a command initialises.

With libtpu installed (the ``tpu`` and ``test`` extras: ``llrmpp plan`` compiles for TPU
through it) on a machine without a TPU, JAX's TPU plugin still starts at the first device
query and prints several lines of warnings about the missing chip. :func:`skip_absent_tpu`
leaves TPU out unless this host has one (``/dev/accel*`` or ``/dev/vfio/N``, the device
nodes of TPU VMs) or the user chose the platforms (``JAX_PLATFORMS``).
"""

from __future__ import annotations

import glob
import importlib.util
import os


def has_tpu_device() -> bool:
    """Whether this host has TPU device nodes."""
    return bool(glob.glob("/dev/accel*") or glob.glob("/dev/vfio/[0-9]*"))


def skip_absent_tpu() -> None:
    """Set ``jax_platforms`` to the CPU (and CUDA, where its plugin is installed) when libtpu
    is installed but no TPU is present and the user set no ``JAX_PLATFORMS``; else nothing.
    Call it before the first device query."""
    if os.environ.get("JAX_PLATFORMS") or importlib.util.find_spec("libtpu") is None or has_tpu_device():
        return
    import jax

    cuda = any(importlib.util.find_spec(m) is not None for m in ("jax_cuda12_plugin", "jax_cuda13_plugin"))
    jax.config.update("jax_platforms", "cuda,cpu" if cuda else "cpu")

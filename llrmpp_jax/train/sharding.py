"""Placing the train state and host batches on data-parallel devices.

Two layouts, one per step wrapper in ``step.py``:

* pmap: every leaf gets a leading device axis -- the state replicated ``[n_dev, ...]``,
  the batch split ``[n_dev, B/n_dev, ...]`` (local devices of this process).
* mesh: a 1-D :class:`jax.sharding.Mesh` with axis ``"batch"`` over all (global) devices;
  the state replicated, each batch leaf a global ``[B_global, ...]`` array built from
  this process's ``[B_local, ...]`` rows (multi-host: ``jax.distributed.initialize``
  first, then every process passes only its own rows).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import jax
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from llrmpp_jax.train.step import AXIS


def _batch_rows(batch: Any, n_shards: int, caller: str) -> int:
    """Common leading size of all batch leaves; raise unless it splits into ``n_shards``."""
    leaves = jax.tree_util.tree_flatten_with_path(batch)[0]
    if not leaves:
        raise ValueError(f"{caller}: batch has no arrays")
    sizes = {jax.tree_util.keystr(p): np.shape(x)[0] if np.ndim(x) else None for p, x in leaves}
    if len(set(sizes.values())) != 1 or None in sizes.values():
        raise ValueError(
            f"{caller}: batch leaves must share a leading batch axis, got leading sizes {sizes}"
        )
    rows = next(iter(sizes.values()))
    if rows % n_shards:
        raise ValueError(
            f"{caller}: batch size {rows} does not divide over {n_shards} devices; "
            f"expected a multiple of {n_shards}"
        )
    return rows


def _put_for_pmap(tree: Any, n: int) -> Any:
    """Place ``[n, ...]`` leaves row by row on the first ``n`` local devices, laid out
    as ``pmap`` lays out its outputs (so feeding them back does not recompile)."""
    mesh = Mesh(np.asarray(jax.local_devices()[:n]), (AXIS,))
    return jax.device_put(tree, NamedSharding(mesh, PartitionSpec(AXIS)))


def shard_for_pmap(batch: Any, n_devices: int | None = None) -> Any:
    """Split every leaf ``[B, ...]`` -> ``[n_dev, B/n_dev, ...]``, row ``i`` on local
    device ``i``. ``n_devices`` defaults to ``jax.local_device_count()``."""
    n = jax.local_device_count() if n_devices is None else n_devices
    rows = _batch_rows(batch, n, "shard_for_pmap")
    split = jax.tree.map(
        lambda x: np.reshape(np.asarray(x), (n, rows // n, *np.shape(x)[1:])), batch
    )
    return _put_for_pmap(split, n)


def replicate_for_pmap(tree: Any, n_devices: int | None = None) -> Any:
    """``n_devices`` copies of every leaf: ``[...]`` -> ``[n_dev, ...]``, one per device."""
    n = jax.local_device_count() if n_devices is None else n_devices
    stacked = jax.tree.map(lambda x: np.broadcast_to(np.asarray(x)[None], (n, *np.shape(x))), tree)
    return _put_for_pmap(stacked, n)


def unreplicate(tree: Any) -> Any:
    """Row 0 of every leaf of a pmap-replicated pytree: ``[n_dev, ...]`` -> ``[...]``."""
    return jax.tree.map(lambda x: x[0], tree)


def make_data_mesh(devices: Sequence[jax.Device] | None = None) -> Mesh:
    """1-D mesh with axis ``"batch"`` over ``devices`` (default: all global devices)."""
    devs = jax.devices() if devices is None else list(devices)
    return Mesh(np.asarray(devs), (AXIS,))


def replicate_on_mesh(tree: Any, mesh: Mesh) -> Any:
    """Every leaf as a global array replicated over ``mesh`` (same value on each process)."""
    sharding = NamedSharding(mesh, PartitionSpec())

    def put(x):
        host = np.asarray(x)
        return jax.make_array_from_callback(host.shape, sharding, lambda idx: host[idx])

    return jax.tree.map(put, tree)


def shard_for_mesh(batch: Any, mesh: Mesh) -> Any:
    """Process-local rows ``[B_local, ...]`` -> global arrays ``[B_local * n_proc, ...]``
    split over the mesh's ``"batch"`` axis. ``B_local`` must divide over the mesh
    devices this process owns."""
    local = sum(d.process_index == jax.process_index() for d in mesh.devices.flat)
    _batch_rows(batch, local, "shard_for_mesh")
    sharding = NamedSharding(mesh, PartitionSpec(AXIS))
    return jax.tree.map(
        lambda x: jax.make_array_from_process_local_data(sharding, np.asarray(x)), batch
    )

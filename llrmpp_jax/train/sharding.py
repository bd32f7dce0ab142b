"""Placing the train state and host batches on a data-parallel device mesh (one layout).

A 1-D :class:`jax.sharding.Mesh` with axis ``"batch"`` (:func:`make_data_mesh`, default:
every global device): the state replicated (:func:`~llrmpp_jax.train.step.state_sharding`),
each batch leaf a global ``[B_global, ...]`` array split over ``"batch"``
(:func:`~llrmpp_jax.train.step.batch_sharding`) built from this process's ``[B_local, ...]``
rows (multi-host: ``jax.distributed.initialize`` first, then every process passes only its
own rows).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import jax
import numpy as np
from jax.sharding import Mesh

from llrmpp_jax.train.step import AXIS, batch_sharding, state_sharding


def _batch_rows(batch: Any, n_shards: int, caller: str) -> int:
    """Common leading size of all batch leaves; raise unless it splits into ``n_shards``."""
    leaves = jax.tree_util.tree_flatten_with_path(batch)[0]
    if not leaves:
        raise ValueError(f"{caller}: batch has no arrays")
    sizes = {jax.tree_util.keystr(p): np.shape(x)[0] if np.ndim(x) else None for p, x in leaves}
    if len(set(sizes.values())) != 1 or None in sizes.values():
        raise ValueError(f"{caller}: batch leaves must share a leading batch axis, got leading sizes {sizes}")
    rows = next(iter(sizes.values()))
    if rows % n_shards:  # pyright: ignore[reportOptionalOperand] -- None is rejected just above
        raise ValueError(
            f"{caller}: batch size {rows} does not divide over {n_shards} devices; expected a multiple of {n_shards}"
        )
    return rows  # pyright: ignore[reportReturnType] -- None is rejected above


def make_data_mesh(devices: Sequence[jax.Device] | None = None) -> Mesh:  # pyright: ignore[reportInvalidTypeForm] -- jax.Device is the device class
    """1-D mesh with axis ``"batch"`` over ``devices`` (default: all global devices)."""
    devs = jax.devices() if devices is None else list(devices)
    return Mesh(np.asarray(devs), (AXIS,))


def replicate_on_mesh(tree: Any, mesh: Mesh) -> Any:
    """Every leaf as a global array replicated over ``mesh`` (same value on each process)."""
    sharding = state_sharding(mesh)

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
    sharding = batch_sharding(mesh)
    return jax.tree.map(lambda x: jax.make_array_from_process_local_data(sharding, np.asarray(x)), batch)


def host_copy(tree: Any) -> Any:
    """Every leaf as a host NumPy array: ``[...]`` of a replicated (or single-device) array,
    on every process (for checkpoints, logs and evaluation)."""
    return jax.tree.map(lambda x: np.asarray(jax.device_get(x)), tree)

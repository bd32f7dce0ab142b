"""Model parameters as an artifact: a params folder, or the newest checkpoint of a training
workdir, loaded the same way and checked against the model config before any compile.

A **params folder** (written by :func:`save_params`, e.g. by ``llrmpp convert``) is an orbax
``StandardCheckpointer`` tree plus ``llrmpp_params.json`` (the model config and the
parameter count), so it needs no experiment file. A **training workdir** holds
``checkpoints/<stage>/<step>/`` (see :mod:`llrmpp_jax.train.checkpoint`), each step
recording the experiment it was trained with. :func:`load_params` tells them apart.
"""

from __future__ import annotations

import dataclasses
import json
import os

import jax
import numpy as np
import orbax.checkpoint as ocp

from llrmpp_jax.config import ModelConfig, from_dict
from llrmpp_jax.errors import UserError
from llrmpp_jax.file_kinds import check_folder, read_json
from llrmpp_jax.model import check_params_fit, expected_shapes, flatten_params
from llrmpp_jax.pretrained import PREFIX, load_pretrained

PARAMS_META = "llrmpp_params.json"
_FORMAT = 1


def save_params(path: str, params, cfg: ModelConfig) -> int:
    """Write ``params`` (for the model of ``cfg``) as a params folder at ``path`` (replaced if
    it exists), wait for orbax to finish, read it back and compare every leaf exactly.
    Returns the number of parameters. ``ValueError`` if the read-back differs."""
    check_params_fit(params, cfg, "save_params")
    path = os.path.abspath(path)
    host = jax.tree.map(np.asarray, params)
    with ocp.StandardCheckpointer() as ckptr:
        ckptr.save(path, host, force=True)
        ckptr.wait_until_finished()
    count = int(sum(np.size(x) for x in jax.tree.leaves(host)))
    with open(os.path.join(path, PARAMS_META), "w") as f:
        json.dump({"format": _FORMAT, "num_params": count, "model": dataclasses.asdict(cfg)}, f, indent=1)
    back, _ = load_params(path)
    mine, theirs = flatten_params(host), flatten_params(back)
    bad = [k for k in mine if k not in theirs or not np.array_equal(mine[k], np.asarray(theirs[k]))]  # pyright: ignore[reportArgumentType] -- the leaves are arrays
    if bad or set(theirs) != set(mine):
        raise UserError(f"{path}: params read back differ from those written (first: {(bad or ['tree'])[0]})")
    return count


def is_params_folder(path: str) -> bool:
    return os.path.isfile(os.path.join(path, PARAMS_META)) or os.path.isfile(os.path.join(path, "_CHECKPOINT_METADATA"))


def _load_params_folder(path: str, cfg: ModelConfig | None) -> tuple[dict, ModelConfig]:
    meta_path = os.path.join(path, PARAMS_META)
    if cfg is None:
        if not os.path.isfile(meta_path):
            raise UserError(f"{path}: bare params folder without {PARAMS_META}; pass --config")
        meta = read_json(meta_path, f"the params folder's {PARAMS_META} (JSON)")
        try:
            cfg = from_dict(ModelConfig, meta["model"])
        except (KeyError, TypeError, AttributeError) as e:
            raise UserError(f"{meta_path}: no model config in it ({type(e).__name__}: {e})") from None
    with ocp.StandardCheckpointer() as ckptr:
        found = ckptr.metadata(path).item_metadata
        if found is None:  # llrmpp_params.json without the arrays orbax writes beside it
            raise UserError(f"{path}: a params folder without its orbax checkpoint (no _METADATA); convert it again")
        saved = found.tree
        check_params_fit(saved, cfg, path)  # pyright: ignore[reportArgumentType] -- cfg is read above when not given
        target = jax.tree.map(lambda m: jax.ShapeDtypeStruct(tuple(m.shape), m.dtype), saved)
        params = ckptr.restore(path, target)
    return params, cfg  # pyright: ignore[reportReturnType] -- as above


def _stage_dirs(workdir: str) -> list[str]:
    base = os.path.join(workdir, "checkpoints") if os.path.isdir(os.path.join(workdir, "checkpoints")) else workdir
    return [os.path.join(base, d) for d in sorted(os.listdir(base)) if os.path.isdir(os.path.join(base, d))]


def _load_workdir(path: str, cfg: ModelConfig | None) -> tuple[dict, ModelConfig]:
    from llrmpp_jax import train as T

    configs = {d: r for d in _stage_dirs(path) if (r := T.recorded_config(d)) is not None}
    if not configs and (r := T.recorded_config(path)) is not None:
        configs = {path: r}  # one stage's folder itself
    if not configs:
        raise UserError(f"no checkpoint in {path} (expected a params folder or a training workdir)")
    stages = list(configs)
    # The curriculum's order from the longest one recorded: a first stage may have been trained
    # with a config that names only it (the shipped model's first stage was), the later ones with the whole.
    orders = [[s["name"] for s in r.get("stages", [])] for r in configs.values() if isinstance(r, dict)]
    order = max(orders, key=len, default=[])
    stage_dir = max(stages, key=lambda d: order.index(os.path.basename(d)) if os.path.basename(d) in order else -1)
    recorded = configs[stage_dir]
    if cfg is None:
        if not isinstance(recorded, dict) or "model" not in recorded:
            raise UserError(f"{stage_dir}: the checkpoint records no model config; pass --config")
        cfg = from_dict(ModelConfig, recorded["model"])
    opt = T.make_optimizer(T.OptimizerConfig(total_steps=1, warmup_steps=0))
    template = jax.eval_shape(lambda p: T.init_train_state(p, opt, jax.random.key(0)), expected_shapes(cfg))  # pyright: ignore[reportArgumentType] -- cfg is read above when not given
    try:
        restored = T.restore_checkpoint(os.path.abspath(stage_dir), template)
    except T.IncompatibleCheckpointError as e:
        raise UserError(str(e)) from None
    if restored is None:
        raise UserError(f"no checkpoint in {stage_dir}")
    return restored.state.params, cfg  # pyright: ignore[reportReturnType] -- as above


def load_params(path: str, cfg: ModelConfig | None = None) -> tuple[dict, ModelConfig]:
    """``(params, model config)`` from a params folder, a training workdir (detected) or a
    shipped model ``pretrained:NAME`` (:mod:`llrmpp_jax.pretrained`, checksum-checked).

    ``cfg`` None: the config recorded in the folder (``llrmpp_params.json``) or with the
    workdir's checkpoint. Given: it must fit the saved shapes (``ValueError`` naming the
    first mismatching parameter path and both shapes), else its own config is used as is.
    """
    if path.startswith(PREFIX):
        return load_pretrained(path[len(PREFIX) :], cfg)
    check_folder(path, "a checkpoint folder (a training workdir or a params folder)")
    if is_params_folder(path):
        return _load_params_folder(os.path.abspath(path), cfg)
    return _load_workdir(path, cfg)

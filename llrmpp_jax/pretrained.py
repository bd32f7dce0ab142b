"""Pretrained weights shipped inside the package (``llrmpp_jax/weights/``), checked on load.

A shipped model ``NAME`` is three files:

* ``NAME.npz``: the parameters in float16 (keys are the parameter paths joined by ``/``);
  float16 keeps the file small (the ``small`` model: ~0.6 MB) and is loaded as float32;
* ``NAME.json``: the model config, the SHA-256 of ``NAME.npz``, the experiment file, commit
  and step it was trained to, its held-out metrics and a recorded forward pass's inputs;
* ``NAME.reference.npz``: that forward pass's output (the RGB of one held-out procedural
  view), so a test can tell that loading and the model still give what was shipped.

:func:`load_pretrained` refuses, in one line naming the file and what differs, a file whose
checksum does not match and a model config other than the caller's. Parameters load anywhere
``llrmpp`` takes ``--checkpoint`` as ``pretrained:NAME`` (``params_io.load_params``).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os

import jax
import numpy as np
from flax.traverse_util import unflatten_dict

from llrmpp_jax.config import ModelConfig, from_dict
from llrmpp_jax.data import ProceduralConfig
from llrmpp_jax.data.preprocess import ViewGeometry, make_sample
from llrmpp_jax.data.synthetic import procedural_scene
from llrmpp_jax.errors import MissingInputError, UserError
from llrmpp_jax.model import check_params_fit, flatten_params, reconstruct, render

WEIGHTS_DIR = os.path.join(os.path.dirname(os.path.abspath(__file__)), "weights")
PREFIX = "pretrained:"
_FORMAT = 1


def _paths(name: str, weights_dir: str) -> tuple[str, str, str]:
    base = os.path.join(weights_dir, name)
    return base + ".npz", base + ".json", base + ".reference.npz"


def available(weights_dir: str = WEIGHTS_DIR) -> list[str]:
    """Names of the shipped models."""
    if not os.path.isdir(weights_dir):
        return []
    return sorted(f[:-5] for f in os.listdir(weights_dir) if f.endswith(".json"))


def sha256(path: str) -> str:
    """Hex SHA-256 of a file's bytes."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def _first_difference(a: object, b: object, where: str = "model") -> str | None:
    """Dotted path and both values of the first difference between two config dicts."""
    if isinstance(a, dict) and isinstance(b, dict):
        for k in sorted(set(a) | set(b)):
            d = _first_difference(a.get(k, "<absent>"), b.get(k, "<absent>"), f"{where}.{k}")
            if d:
                return d
        return None
    norm = lambda x: list(x) if isinstance(x, tuple) else x  # noqa: E731  JSON reads tuples as lists
    return None if norm(a) == norm(b) else f"{where}: shipped {a!r}, expected {b!r}"


def _config_json(cfg: ModelConfig) -> dict:
    """``cfg`` as it reads back from JSON (tuples become lists)."""
    return json.loads(json.dumps(dataclasses.asdict(cfg)))


def read_meta(name: str, weights_dir: str = WEIGHTS_DIR) -> dict:
    """The ``NAME.json`` record. ``FileNotFoundError`` listing the shipped names."""
    _, meta_path, _ = _paths(name, weights_dir)
    if not os.path.isfile(meta_path):
        raise MissingInputError(
            f"no shipped model {name!r} in {weights_dir} (shipped: {', '.join(available(weights_dir)) or 'none'})"
        )
    with open(meta_path) as f:
        return json.load(f)


def load_pretrained(
    name: str, cfg: ModelConfig | None = None, weights_dir: str = WEIGHTS_DIR
) -> tuple[dict, ModelConfig]:
    """``(float32 params, model config)`` of the shipped model ``name``.

    ``ValueError`` in one line naming the file if its SHA-256 differs from the record, or if
    ``cfg`` is given and differs from the shipped config (the first differing field, both
    values)."""
    npz_path, meta_path, _ = _paths(name, weights_dir)
    meta = read_meta(name, weights_dir)
    got = sha256(npz_path)
    if got != meta["sha256"]:
        raise UserError(
            f"{npz_path}: checksum mismatch: sha256 {got[:16]}..., {os.path.basename(meta_path)} "
            f"records {meta['sha256'][:16]}... (a corrupt or replaced weights file)"
        )
    # A field the record lacks (added to ModelConfig after shipping) takes its default,
    # which keeps the behaviour the weights were trained with.
    try:
        shipped_cfg = from_dict(ModelConfig, meta["model"])
    except ValueError as e:  # a field this version does not know
        raise UserError(f"{npz_path}: weights are for another model config: {e}") from None
    if cfg is not None:
        diff = _first_difference(_config_json(shipped_cfg), _config_json(cfg))
        if diff:
            raise UserError(f"{npz_path}: weights are for another model config: {diff}")
    with np.load(npz_path, allow_pickle=False) as z:
        params = unflatten_dict({k: z[k].astype(np.float32) for k in z.files}, sep="/")
    check_params_fit(params, shipped_cfg, npz_path)
    return jax.tree.map(np.asarray, params), shipped_cfg


def reference_forward(params: dict, cfg: ModelConfig, ref: dict) -> np.ndarray:
    """RGB ``[H, W, 3]`` of the recorded forward pass ``ref`` (``NAME.json``'s "reference":
    procedural scene seed, size, frame count, input and target frames)."""
    h, w = ref["height"], ref["width"]
    scene = procedural_scene(ref["seed"], ProceduralConfig(height=h, width=w, num_frames=ref["num_frames"]))
    geom = ViewGeometry(resize_h=h, multiple=cfg.size_multiple, square_crop=True)
    s = make_sample(scene, np.asarray(ref["inputs"]), np.asarray([ref["target"]]), geom)

    @jax.jit
    def run(params, s):
        g = reconstruct(params, cfg, s["input_images"][None], s["input_c2w"][None], s["input_intrinsics"][None])
        return render(params, cfg, g, s["target_c2w"][None], s["target_intrinsics"][None], h, w).images["rgb"][0, 0]

    return np.asarray(run(params, {k: v for k, v in s.items() if k != "scene_scale"}))


def export_pretrained(
    params: dict, cfg: ModelConfig, name: str, record: dict, reference: dict, weights_dir: str = WEIGHTS_DIR
) -> dict:
    """Write the shipped model ``name`` (the three files of the module docstring) and return
    its ``NAME.json`` record. ``record`` adds provenance (experiment, commit, steps,
    metrics); ``reference`` is the forward pass to record (see :func:`reference_forward`).
    The reference output is computed from the float16-rounded parameters, as they load."""
    check_params_fit(params, cfg, f"export_pretrained({name!r})")
    os.makedirs(weights_dir, exist_ok=True)
    npz_path, meta_path, ref_path = _paths(name, weights_dir)
    half = {k: np.asarray(v, np.float16) for k, v in flatten_params(jax.device_get(params)).items()}
    if not all(np.isfinite(v).all() for v in half.values()):
        raise UserError(f"export_pretrained({name!r}): a parameter overflows float16")
    np.savez(npz_path, **half)  # pyright: ignore[reportArgumentType] -- arrays by keyword; pyright matches the ** to allow_pickle
    loaded = unflatten_dict({k: v.astype(np.float32) for k, v in half.items()}, sep="/")
    np.savez(ref_path, rgb=reference_forward(loaded, cfg, reference))
    meta = dict(
        record,
        format=_FORMAT,
        name=name,
        sha256=sha256(npz_path),
        num_params=int(sum(v.size for v in half.values())),
        dtype="float16",
        model=_config_json(cfg),
        reference=reference,
    )
    with open(meta_path, "w") as f:
        json.dump(meta, f, indent=1)
    return meta

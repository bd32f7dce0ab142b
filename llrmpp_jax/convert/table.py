"""Table-driven conversion of PyTorch ``state_dict`` tensors into nested JAX params.

A :class:`Rule` maps every PyTorch key that fully matches its regular expression to a
'/'-separated Flax parameter path (a template filled from the regex's named groups) and
applies a layout transform (e.g. ``linear``: (out, in) -> (in, out)). Conversion is
strict by default: every kept key must match exactly one rule, and when an expected
parameter tree (``jax.eval_shape`` of the model's init) is given, every expected leaf
must be produced with the expected shape. Errors list *all* offending keys at once.
"""

from __future__ import annotations

import pickle
import re
import zipfile
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
from flax.traverse_util import flatten_dict, unflatten_dict

from llrmpp_jax.errors import MissingInputError, UserError
from llrmpp_jax.file_kinds import check_torch_file

Transform = Callable[[np.ndarray], np.ndarray]


def identity(w: np.ndarray) -> np.ndarray:
    return w


def linear(w: np.ndarray) -> np.ndarray:
    """``nn.Linear.weight`` (out, in) -> Flax ``Dense.kernel`` (in, out)."""
    return w.T


def conv1d_depthwise(w: np.ndarray) -> np.ndarray:
    """Depthwise ``nn.Conv1d.weight`` (C, 1, K) -> (K, C) taps, tap K-1 on the current token."""
    return w[:, 0, :].T


def conv2d(w: np.ndarray) -> np.ndarray:
    """``nn.Conv2d.weight`` (out, in/groups, kh, kw) -> Flax ``Conv.kernel`` (kh, kw, in/groups, out)."""
    return w.transpose(2, 3, 1, 0)


@dataclass(frozen=True)
class Rule:
    """``pattern`` (full-match regex over torch keys) -> ``target`` path template."""

    pattern: str
    target: str
    transform: Transform = identity

    def match(self, key: str) -> str | None:
        m = re.fullmatch(self.pattern, key)
        return None if m is None else self.target.format(**m.groupdict())


def convert_state_dict(
    state_dict: Mapping[str, Any],
    rules: Iterable[Rule],
    *,
    expected: Mapping[str, Any] | None = None,
    keep_prefixes: tuple[str, ...] | None = None,
    dtype: np.dtype | type = np.float32,
    source: str = "state_dict",
) -> dict[str, Any]:
    """Convert a PyTorch-named mapping of arrays into a nested parameter dict.

    Args:
      state_dict: torch key -> array (NumPy or torch tensor; converted with ``np.asarray``).
      rules: the table; each key must match exactly one rule.
      expected: optional nested dict of leaves with ``.shape`` (e.g. ``jax.eval_shape``
        output); if given, missing/extra leaves and shape mismatches are errors.
      keep_prefixes: if given, keys not starting with one of these are dropped first
        (training checkpoints carry frozen loss networks that are not model params).
      dtype: dtype of the produced arrays.
      source: name used in error messages (e.g. the checkpoint file).

    Returns:
      Nested dict of NumPy arrays, ready for ``jax.device_put``.

    Raises:
      ValueError: listing every unmatched, doubly matched, missing, unexpected or
        wrongly shaped entry.
    """
    rules = list(rules)
    flat: dict[str, np.ndarray] = {}
    problems: list[str] = []
    for key, value in state_dict.items():
        if keep_prefixes is not None and not key.startswith(keep_prefixes):
            continue
        hits = [(r, t) for r in rules if (t := r.match(key)) is not None]
        if not hits:
            problems.append(f"no rule for key {key!r}")
            continue
        if len(hits) > 1:
            problems.append(f"key {key!r} matches several rules: {[t for _, t in hits]}")
            continue
        rule, target = hits[0]
        arr = np.asarray(value.detach().cpu().numpy() if hasattr(value, "detach") else value)
        if target in flat:
            problems.append(f"two keys map to {target!r} (second: {key!r})")
        flat[target] = rule.transform(arr).astype(dtype)
    if expected is not None:
        want = flatten_dict(dict(expected), sep="/")
        for path in sorted(set(want) - set(flat)):
            problems.append(f"parameter {path!r} {tuple(want[path].shape)} missing")  # pyright: ignore[reportAttributeAccessIssue] -- a leaf of the params tree is an array
        for path in sorted(set(flat) - set(want)):
            problems.append(f"{path!r} given, but the model has no such parameter")
        for path in sorted(set(want) & set(flat)):
            if tuple(want[path].shape) != flat[path].shape:  # pyright: ignore[reportAttributeAccessIssue] -- a leaf of the params tree is an array
                problems.append(
                    f"parameter {path!r}: the model's shape {tuple(want[path].shape)}, the file's {flat[path].shape}"  # pyright: ignore[reportAttributeAccessIssue] -- a leaf of the params tree is an array
                )
    if problems:
        shown = "; ".join(problems[:3])
        more = f" (and {len(problems) - 3} more)" if len(problems) > 3 else ""
        raise UserError(f"cannot convert {source}: {len(problems)} problem(s): {shown}{more}")
    return unflatten_dict(flat, sep="/")


def load_torch_state_dict(path: str) -> dict[str, np.ndarray]:
    """Read a ``.pt``/``.pth`` (torch, CPU) or ``.npz`` file into key -> NumPy array.

    A training checkpoint ``{'model': state_dict, 'optimizer': ...}`` is unwrapped.
    torch is imported lazily (the ``torch`` extra) and only for ``.pt``/``.pth``.
    """
    import os

    if not os.path.exists(path):
        raise MissingInputError(f"checkpoint file not found: {path}")
    # The content decides, not the extension: both formats may be zip archives.
    names = None
    if zipfile.is_zipfile(path):
        try:
            with zipfile.ZipFile(path) as z:
                names = z.namelist()
        except (zipfile.BadZipFile, OSError) as e:
            raise UserError(f"{path}: a damaged zip archive ({e}); expected a .npz or a torch .pt") from None
    if names is not None and any(n.endswith(".npy") for n in names):
        try:
            with np.load(path, allow_pickle=False) as z:
                return {k: z[k] for k in z.files}
        except (ValueError, OSError, EOFError, zipfile.BadZipFile) as e:
            raise UserError(f"{path}: a damaged .npz archive ({e})") from None
    if names is None and path.endswith(".npz"):
        raise UserError(f"{path}: not a .npz archive (not a zip file: truncated or another format)")
    check_torch_file(path)  # a photo or a text file is named as such, before torch unpickles it
    try:
        import torch
    except ImportError as e:  # pragma: no cover - depends on the environment
        raise ImportError(f"reading {path} needs torch: pip install 'llrmpp-jax[torch]'") from e
    try:
        obj = torch.load(path, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError:
        raise UserError(
            f"{path}: holds Python objects other than tensors, which torch will not unpickle safely "
            "(weights_only=True); save the weights alone with torch.save(model.state_dict(), path)"
        ) from None
    except (RuntimeError, EOFError, OSError) as e:
        first = (str(e).splitlines() or [type(e).__name__])[0]
        raise UserError(f"{path}: not a readable torch checkpoint or .npz archive ({first})") from None
    if isinstance(obj, Mapping) and "model" in obj and isinstance(obj["model"], Mapping):
        obj = obj["model"]
    if not isinstance(obj, Mapping):
        raise UserError(f"{path}: expected a state_dict (mapping of tensors), got {type(obj).__name__}")
    return {k: v.detach().cpu().numpy() for k, v in obj.items() if hasattr(v, "detach")}

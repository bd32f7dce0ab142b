"""Orbax checkpoints of a :class:`TrainState` with a verified manifest.

Layout: ``directory/<step>/`` is one orbax ``CheckpointManager`` step (written to a
temporary folder and renamed when complete, so a kill mid-save leaves no half step)
with two items -- ``state`` (every state leaf, keyed ``leaf_00000``...) and ``meta``
(JSON: leaf paths/shapes/dtypes, the data-iterator position, the run config) -- plus
``llrmpp_manifest.json``: size and SHA-256 of every file of the step, written
atomically once orbax has finished. A step without a manifest (killed between the two)
or whose files no longer match it (truncated, bit-flipped, deleted) is rejected with a
warning and the previous step is restored instead. The last ``keep`` steps are kept.

Saving is synchronous: the manifest can only be computed from complete files.
"""

from __future__ import annotations

import contextlib
import dataclasses
import errno
import hashlib
import json
import logging
import os
import re
import shutil
import sys
import threading
import time
import warnings
from collections.abc import Iterator
from pathlib import Path
from typing import Any, NamedTuple

import jax
import numpy as np
import orbax.checkpoint as ocp
from jax.experimental import multihost_utils

from llrmpp_jax.errors import OutOfSpaceError, UserError
from llrmpp_jax.train.state import TrainState

MANIFEST = "llrmpp_manifest.json"
_FORMAT = 1


class CorruptCheckpointError(UserError, RuntimeError):
    """A checkpoint step whose files are missing, truncated or altered."""


class IncompatibleCheckpointError(UserError):
    """A checkpoint whose state tree (paths, shapes, dtypes) differs from the model's."""


class Restored(NamedTuple):
    """What :func:`restore_checkpoint` returns."""

    state: TrainState
    step: int
    data_state: dict
    config: Any


def _flatten(state: TrainState) -> tuple[list[str], list[Any], Any]:
    """Leaf path strings, leaves and treedef of ``state``."""
    with_path, treedef = jax.tree_util.tree_flatten_with_path(state)
    paths = [jax.tree_util.keystr(p) for p, _ in with_path]
    return paths, [leaf for _, leaf in with_path], treedef


def _leaf_name(i: int) -> str:
    return f"leaf_{i:05d}"


@contextlib.contextmanager
def _manager(directory: Path) -> Iterator[ocp.CheckpointManager]:
    """An orbax manager of ``directory`` that has finished its start-up clean-up.

    With ``cleanup_tmp_directories`` orbax deletes unfinished steps of an earlier run in a
    background thread that ``close()`` does not join; a command that stops right after (a
    one-line user error) would then print that thread's traceback at interpreter exit. So
    the clean-up is awaited here, before the manager is used.
    """
    options = ocp.CheckpointManagerOptions(
        enable_async_checkpointing=False,
        cleanup_tmp_directories=True,
        create=True,
    )
    with ocp.CheckpointManager(directory, options=options) as mngr:
        mngr._maybe_await_cleanup_tmp_directory()  # orbax has no public way to wait for it
        yield mngr


def _file_digest(path: Path) -> str:
    with open(path, "rb") as f:
        return hashlib.file_digest(f, "sha256").hexdigest()


def _step_files(step_dir: Path) -> list[Path]:
    return sorted(p for p in step_dir.rglob("*") if p.is_file() and p.name != MANIFEST)


def _write_manifest(step_dir: Path) -> None:
    """Record size and SHA-256 of every file under ``step_dir`` (atomic replace)."""
    files = {
        str(p.relative_to(step_dir)): {"size": p.stat().st_size, "sha256": _file_digest(p)}
        for p in _step_files(step_dir)
    }
    tmp = step_dir / (MANIFEST + ".tmp")
    with open(tmp, "w") as f:
        json.dump({"format": _FORMAT, "files": files}, f, indent=1)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, step_dir / MANIFEST)


def verify_checkpoint(directory: str | os.PathLike, step: int) -> None:
    """Raise :class:`CorruptCheckpointError` unless every file of ``step`` matches its
    manifest (present, same size, same SHA-256)."""
    step_dir = Path(directory) / str(step)
    manifest = step_dir / MANIFEST
    if not manifest.is_file():
        raise CorruptCheckpointError(f"checkpoint {step_dir} has no {MANIFEST}: the save did not complete")
    try:
        files = json.loads(manifest.read_text())["files"]
    except (json.JSONDecodeError, KeyError) as err:
        raise CorruptCheckpointError(f"checkpoint {step_dir}: unreadable {MANIFEST} ({err})") from None
    for rel, expect in files.items():
        path = step_dir / rel
        if not path.is_file():
            raise CorruptCheckpointError(f"checkpoint {step_dir}: file {rel} is missing")
        size = path.stat().st_size
        if size != expect["size"]:
            raise CorruptCheckpointError(
                f"checkpoint {step_dir}: file {rel} has {size} bytes, expected "
                f"{expect['size']} (truncated or overwritten)"
            )
        if _file_digest(path) != expect["sha256"]:
            raise CorruptCheckpointError(f"checkpoint {step_dir}: file {rel} fails its SHA-256 check (corrupted)")


def _config_json(config: Any) -> Any:
    """``config`` as JSON data (dataclasses via ``asdict``); raise if not serialisable."""
    data = dataclasses.asdict(config) if dataclasses.is_dataclass(config) else config  # pyright: ignore[reportArgumentType] -- an instance here, not a class
    try:
        return json.loads(json.dumps(data))
    except TypeError as err:
        raise UserError(f"save_checkpoint: config is not JSON-serialisable ({err})") from None


def save_checkpoint(
    directory: str | os.PathLike,
    state: TrainState,
    *,
    data_state: dict | None = None,
    config: Any = None,
    keep: int = 3,
) -> Path:
    """Save ``state`` as step ``int(state.step)``; return the step folder.

    ``state`` is one copy of the state (host arrays, or the runner's global arrays
    replicated on a mesh), not a stack of per-device copies. ``data_state``: JSON mapping that
    restarts the data iterator (e.g. ``{"position": 1200}``). ``config``: the run config
    (dataclass or JSON data). ``keep``: how many most recent steps to keep. A step
    already present (e.g. one rejected on restore) is replaced.
    """
    if keep < 1:
        raise ValueError(f"save_checkpoint: keep={keep} must be >= 1")
    if not isinstance(state, TrainState):
        raise ValueError(f"save_checkpoint: state must be a TrainState, got {type(state)}")
    if np.ndim(state.step) != 0:
        raise ValueError(
            f"save_checkpoint: state.step has shape {np.shape(state.step)}, expected (); "
            f"save one copy of the state, not per-device copies stacked"
        )
    directory = Path(directory).absolute()
    step = int(state.step)
    paths, leaves, _ = _flatten(state)
    meta = {
        "format": _FORMAT,
        "step": step,
        "leaves": [[p, list(np.shape(x)), str(np.dtype(x.dtype))] for p, x in zip(paths, leaves)],
        "data_state": json.loads(json.dumps(data_state or {})),
        "config": _config_json(config),
    }
    items = {_leaf_name(i): x for i, x in enumerate(leaves)}
    step_dir = directory / str(step)
    with _manager(directory) as mngr:
        if step in mngr.all_steps():
            mngr.delete(step)
        try:
            with _failed_writes_reported_once():
                mngr.save(
                    step,
                    args=ocp.args.Composite(state=ocp.args.StandardSave(items), meta=ocp.args.JsonSave(meta)),
                )
                mngr.wait_until_finished()
                if jax.process_index() == 0:
                    _write_manifest(step_dir)
        except Exception as e:
            code = _out_of_space_errno(e)
            if code is None:
                raise
            _remove_unfinished(directory, step)
            earlier = sorted(s for s in mngr.all_steps() if s != step)
            kept = (
                f"the newest complete checkpoint (step {earlier[-1]}) is intact" if earlier else "no earlier checkpoint"
            )
            raise OutOfSpaceError(
                f"checkpoint step {step} not saved in {directory}: {os.strerror(code)} ({_SPACE[code]}); "
                f"{kept}; free space and run the same command again to resume"
            ) from None
        if jax.process_count() > 1:
            multihost_utils.sync_global_devices(f"llrmpp_manifest_{step}")
        # Prune only now that the new step is verifiable (orbax's own max_to_keep would
        # delete the previous good step before the manifest exists).
        for old in sorted(mngr.all_steps(), reverse=True)[keep:]:
            mngr.delete(old)
    return step_dir


def _remove_unfinished(directory: Path, step: int, quiet_s: float = 0.5, limit_s: float = 10.0) -> None:
    """Remove what a failed save of ``step`` left: orbax renames a step into place only
    when complete, so its temporary folder (and maybe a manifest-less step, which restore
    rejects). Tensorstore's writer threads of the failed save can still be creating files
    there after the failure reached us (they are not Python threads to join), so removal
    repeats until nothing has reappeared for ``quiet_s`` seconds (at most ``limit_s``)."""

    def leftovers() -> list[Path]:
        found = list(directory.glob(f"{step}.orbax-checkpoint-tmp*"))
        step_dir = directory / str(step)
        return found + ([step_dir] if step_dir.exists() and not (step_dir / MANIFEST).exists() else [])

    deadline = time.monotonic() + limit_s
    while time.monotonic() < deadline:
        for path in leftovers():
            shutil.rmtree(path, ignore_errors=True)
        time.sleep(quiet_s)
        if not leftovers():
            return


# Write failures that mean the disk (or a limit on it) is full, and what to tell the user.
_SPACE = {
    errno.ENOSPC: "the disk is full",
    errno.EDQUOT: "the disk quota is used up",
    errno.EFBIG: "a file-size limit was reached",
}
# Orbax writes through tensorstore, whose errors are ValueErrors with the OS error code in
# their text.
_TENSORSTORE_ERRNO = re.compile(r"os_error_code='(\d+)'")


def _out_of_space_errno(e: BaseException | None) -> int | None:
    """The errno of ``e`` (or of an exception in its cause chain) if it is a write that ran
    out of space, else None."""
    while e is not None:
        code = e.errno if isinstance(e, OSError) else None
        match = _TENSORSTORE_ERRNO.search(str(e))
        code = int(match.group(1)) if code is None and match else code
        if code in _SPACE:
            return code
        e = e.__cause__ or e.__context__
    return None


def _is_closed_loop_echo(error: BaseException | None) -> bool:
    return isinstance(error, RuntimeError) and str(error) == "Event loop is closed"


@contextlib.contextmanager
def _failed_writes_reported_once() -> Iterator[None]:
    """Around a save: when one write fails, every orbax worker thread of the save logs the
    failure again (an absl ERROR with its traceback) and tensorstore's late callbacks into
    the closed event loop raise "Event loop is closed" as unraisable exceptions, some after
    the save has returned. :func:`save_checkpoint` reports the failure itself, once. So
    while saving, absl's ERROR records are held back and replayed only if the save
    succeeds; closed-loop echoes, and only they, are dropped from the start of the save (and,
    after a failure, for the rest of the process); on failure the save's threads are joined
    first, so nothing of it runs on."""
    absl_logger = logging.getLogger("absl")
    held: list[logging.LogRecord] = []

    class _Hold(logging.Filter):
        def filter(self, record: logging.LogRecord) -> bool:
            held.append(record)
            return False

    hold = _Hold()
    before = set(threading.enumerate())
    previous, previous_thread = sys.unraisablehook, threading.excepthook
    # Installed before the save: an echo can come from another thread before the failure
    # reaches this one (as an unraisable exception or a thread's uncaught one).
    sys.unraisablehook = lambda u: None if _is_closed_loop_echo(u.exc_value) else previous(u)
    threading.excepthook = lambda a: None if _is_closed_loop_echo(a.exc_value) else previous_thread(a)
    absl_logger.addFilter(hold)
    try:
        yield
    except BaseException:
        for t in set(threading.enumerate()) - before:
            if t is not threading.current_thread() and not t.daemon:
                t.join(timeout=60)
        raise  # the echo filter stays: late callbacks may still come
    else:
        sys.unraisablehook, threading.excepthook = previous, previous_thread
        for record in held:
            absl_logger.handle(record)
    finally:
        absl_logger.removeFilter(hold)


def _check_compatible(step_dir: Path, saved: list, paths: list[str], leaves: list) -> None:
    """Raise :class:`IncompatibleCheckpointError` (one line) if the trees differ."""
    ours = {p: (list(np.shape(x)), str(np.dtype(x.dtype))) for p, x in zip(paths, leaves)}
    theirs = {p: (shape, dtype) for p, shape, dtype in saved}
    problems = [f"{p} missing from the checkpoint" for p in ours if p not in theirs]
    problems += [f"{p} is in the checkpoint but not the model" for p in theirs if p not in ours]
    problems += [
        f"{p} is {tuple(theirs[p][0])} {theirs[p][1]} in the checkpoint, {tuple(ours[p][0])} {ours[p][1]} in the model"
        for p in ours
        if p in theirs and theirs[p] != ours[p]
    ]
    if problems:
        raise IncompatibleCheckpointError(
            f"checkpoint {step_dir} does not fit this model (different config?): "
            f"{len(problems)} leaf mismatch(es), first: {problems[0]}"
        )


def _restore_step(mngr: ocp.CheckpointManager, directory: Path, step: int, template) -> Restored:
    paths, leaves, treedef = _flatten(template)
    meta = mngr.restore(step, args=ocp.args.Composite(meta=ocp.args.JsonRestore())).meta  # pyright: ignore[reportAttributeAccessIssue] -- orbax's Composite result is typed as a Mapping; it has the items as attributes
    _check_compatible(directory / str(step), meta["leaves"], paths, leaves)
    abstract = {
        _leaf_name(i): jax.ShapeDtypeStruct(np.shape(x), x.dtype, sharding=getattr(x, "sharding", None))
        for i, x in enumerate(leaves)
    }
    items = mngr.restore(step, args=ocp.args.Composite(state=ocp.args.StandardRestore(abstract))).state  # pyright: ignore[reportAttributeAccessIssue] -- orbax's Composite result is typed as a Mapping; it has the items as attributes
    restored = [items[_leaf_name(i)] for i in range(len(leaves))]
    return Restored(
        state=jax.tree_util.tree_unflatten(treedef, restored),
        step=step,
        data_state=meta["data_state"],
        config=meta["config"],
    )


def restore_checkpoint(
    directory: str | os.PathLike, template: TrainState, *, step: int | None = None
) -> Restored | None:
    """Restore a verified checkpoint into the structure, dtypes and shardings of
    ``template`` (a fresh state, or its ``jax.eval_shape``).

    ``step=None``: the newest step that passes :func:`verify_checkpoint`; each newer
    step that fails is reported with a ``UserWarning`` and skipped. Returns ``None`` if
    ``directory`` holds no checkpoint; raises :class:`CorruptCheckpointError` if none
    passes, or if the requested ``step`` fails, and
    :class:`IncompatibleCheckpointError` if the state tree differs from ``template``.
    """
    directory = Path(directory).absolute()
    if not directory.is_dir():
        return None
    with _manager(directory) as mngr:
        steps = sorted(mngr.all_steps(), reverse=True)
        if step is not None:
            if step not in steps:
                raise UserError(f"restore_checkpoint: no step {step} in {directory} (steps: {sorted(steps)})")
            verify_checkpoint(directory, step)
            return _restore_step(mngr, directory, step, template)
        if not steps:
            return None
        rejected = []
        for candidate in steps:
            try:
                verify_checkpoint(directory, candidate)
            except CorruptCheckpointError as err:
                rejected.append(str(err))
                warnings.warn(f"{err}; falling back to an earlier checkpoint", stacklevel=2)
                continue
            return _restore_step(mngr, directory, candidate, template)
    raise CorruptCheckpointError(f"no valid checkpoint in {directory}: " + "; ".join(rejected))


def recorded_config(directory: str | os.PathLike) -> Any:
    """The run config saved with the newest step under ``directory`` (JSON data), or None
    when it holds no step. Read before restoring, to build the restore template."""
    directory = Path(directory).absolute()
    if not directory.is_dir():
        return None
    with _manager(directory) as mngr:
        steps = mngr.all_steps()
        if not steps:
            return None
        return mngr.restore(max(steps), args=ocp.args.Composite(meta=ocp.args.JsonRestore())).meta["config"]  # pyright: ignore[reportAttributeAccessIssue] -- orbax's Composite result is typed as a Mapping; it has the items as attributes

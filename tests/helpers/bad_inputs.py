"""Inputs for the command line's error paths (``tests/test_bad_inputs.py``,
``tests/test_cli_fuzz.py``): a tiny valid colour-mode ``.gs`` scene, files broken from it,
and :func:`run_cli`, ``llrmpp_jax.cli.main`` in this process with its exit status and stderr."""

from __future__ import annotations

import contextlib
import io
import os

import numpy as np

from llrmpp_jax.capture import SavedScene, save_gs
from llrmpp_jax.cli import main
from llrmpp_jax.data import in_memory_scene
from llrmpp_jax.data.formats import write_nerfstudio_scene
from llrmpp_jax.data.image_io import write_image
from tests.helpers.wide_gaussians import INTRINSICS, SIZE, wide_colour_scene


def tiny_saved_scene(rng: np.random.Generator, n: int = 20) -> SavedScene:
    """A colour-mode scene (SH degree 0, the tiny model) of ``n`` Gaussians and two frames
    of 64x64, frame 0 the input and frame 1 the target; its capture does not exist."""
    g, cfg, c2w = wide_colour_scene(rng, n)
    return SavedScene(
        gaussians=g,
        model=cfg,
        c2w=c2w,
        intrinsics=np.tile(INTRINSICS, (2, 1)),
        world_from_scene=np.eye(4),
        frame_names=("images/a.png", "images/b.png"),
        inputs=np.array([0]),
        targets=np.array([1]),
        image_hw=(SIZE, SIZE),
        resized_hw=(SIZE, SIZE),
        crop_box=(0, 0, SIZE, SIZE),
        scene_path="/no/capture",
        scene_format="colmap",
    )


def write_gs(path: str, rng: np.random.Generator, **arrays: np.ndarray) -> str:
    """A ``.gs`` file of :func:`tiny_saved_scene` at ``path`` with ``arrays`` written in place
    of (or beside) its own, by ``np.savez`` as ``save_gs`` writes them; returns ``path``."""
    save_gs(path, tiny_saved_scene(rng))
    if arrays:
        with np.load(path) as z:
            kept = {k: z[k] for k in z.files}
        with open(path, "wb") as f:
            np.savez(f, **{**kept, **arrays})  # pyright: ignore[reportArgumentType] -- arrays by keyword
    return path


def write_photo(path: str, rng: np.random.Generator) -> str:
    """A real 16x16 JPEG photo at ``path`` (whatever its extension); returns ``path``."""
    tmp = path + ".tmp.jpg"
    write_image(tmp, rng.uniform(size=(16, 16, 3)).astype(np.float32))
    os.replace(tmp, path)
    return path


def tiny_capture(path: str, rng: np.random.Generator, image_ext: str = ".png") -> str:
    """A nerfstudio capture at ``path`` of 6 frames of 32x48 (8-bit ``image_ext``) on a line
    of cameras; returns ``path``."""
    c2w = np.tile(np.eye(4), (6, 1, 1))
    c2w[:, 0, 3] = np.linspace(-1, 1, 6)
    scene = in_memory_scene("t", rng.uniform(0.1, 0.9, (6, 32, 48, 3)), c2w, np.tile([[40.0, 40, 24, 16]], (6, 1)))
    write_nerfstudio_scene(scene, path, image_ext=image_ext, bits=8)
    return path


def run_cli(argv: list[str]) -> tuple[int, list[str]]:
    """``(exit status, stderr lines)`` of ``llrmpp ARGV`` run in this process; a parser error
    (``SystemExit``) gives its status. Any other exception propagates: in the console it would
    be a traceback."""
    err, out = io.StringIO(), io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(out):
        try:
            status = main(argv)
        except SystemExit as e:
            status = e.code if isinstance(e.code, int) else 2
    return status, err.getvalue().strip().splitlines()


def error_line(lines: list[str]) -> str:
    """The one ``error:`` line of a refused command (argparse prints its usage above it)."""
    errors = [x for x in lines if "error:" in x]
    assert len(errors) == 1 and lines[-1] == errors[0], lines
    assert not any("Traceback" in x for x in lines), lines
    return errors[0]

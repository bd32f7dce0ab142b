"""Camera poses from photos or a video (``llrmpp_jax.capture.poses``, pycolmap): a real
capture's photos register and read back as a capture; a video's frames too; photos that
share nothing fail in one line; bad inputs are one line; importing pycolmap leaves the
process's crash handlers as they were."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import warnings

import numpy as np
import pytest

from llrmpp_jax.capture.poses import PosesConfig, estimate_poses, extract_frames
from llrmpp_jax.cli import main
from llrmpp_jax.data.formats import read_scene
from llrmpp_jax.data.image_io import write_image
from llrmpp_jax.errors import MissingInputError, UserError
from tests.helpers.bad_inputs import error_line, run_cli
from tests.helpers.environment import shared_path
from tests.helpers.photos import FOX, fox_photos, fox_video


def test_photos_register_and_read_back_as_a_capture(tmp_path, capsys):
    names = fox_photos(tmp_path / "photos")
    out = str(tmp_path / "capture")
    assert main(["poses", "--images", str(tmp_path / "photos"), "--out", out, "--max-image-size", "480"]) == 0
    printed = capsys.readouterr().out
    report = json.load(open(os.path.join(out, "poses_report.json")))
    assert report["given"] == FOX and report["registered"] >= FOX - 1, report
    assert report["matcher"] == "exhaustive" and report["shared_camera"]
    assert 0 < report["mean_reprojection_error_px"] < 2.0 and report["mean_track_length"] > 2.0, report
    assert f"registered {report['registered']} of {FOX} images" in printed
    scene = read_scene(out, "auto")  # the standard COLMAP layout every command reads
    assert len(scene) == report["registered"]
    # The recovered cameras are a rigid motion + scale of the capture's own (nerfstudio) poses:
    # the ratios of camera-centre distances agree.
    with warnings.catch_warnings():  # the fox capture lists 17 frames it does not ship
        warnings.simplefilter("ignore", UserWarning)
        fox = read_scene(shared_path("data", "fox"), "auto")
    ours = {os.path.basename(n): c[:3, 3] for n, c in zip(scene.frame_names, scene.c2w)}
    theirs = {os.path.basename(n): c[:3, 3] for n, c in zip(fox.frame_names, fox.c2w) if os.path.basename(n) in ours}
    keys = sorted(set(ours) & set(theirs))
    a = np.array([ours[k] for k in keys])
    b = np.array([theirs[k] for k in keys])
    da = np.linalg.norm(a[:, None] - a[None], axis=-1)
    db = np.linalg.norm(b[:, None] - b[None], axis=-1)
    iu = np.triu_indices(len(keys), 1)
    ratio = da[iu] / db[iu]
    assert np.std(ratio) / np.mean(ratio) < 0.05, ratio  # 5%: COLMAP vs nerfstudio's own solve
    assert sorted(os.listdir(os.path.join(out, "images"))) == names


def test_a_video_becomes_frames_and_poses(tmp_path):
    video = str(tmp_path / "walk.mp4")
    assert fox_video(video, size=320, fps=5) == FOX
    names = extract_frames(video, str(tmp_path / "frames"), fps=5, progress=lambda _: None)
    assert len(names) == FOX  # 2 s at 5 frames a second
    report = estimate_poses(
        None, str(tmp_path / "capture"), PosesConfig(max_image_size=320), video=video, fps=5, progress=lambda _: None
    )
    assert report.matcher == "sequential" and report.registered >= FOX - 2, report


def test_photos_that_share_nothing_fail_in_one_line(tmp_path, rng, capsys):
    folder = tmp_path / "noise"
    folder.mkdir()
    for i in range(4):
        write_image(str(folder / f"{i}.png"), rng.uniform(size=(96, 128, 3)).astype(np.float32))
    out = tmp_path / "capture"
    assert main(["poses", "--images", str(folder), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "of 4 images registered (need 3)" in err[0] and "overlap" in err[0], err
    assert not (out / "sparse").exists()


@pytest.mark.parametrize(
    "args, message",
    [
        (["--images", "/nonexistent/photos"], "--images: folder not found"),
        (["--video", "/nonexistent/walk.mp4"], "--video: file not found"),
        (["--images", "{empty}"], "no images"),
        (["--images", "{empty}", "--max-image-size", "8"], "argument --max-image-size: must be an integer in [64,"),
        (["--images", "{empty}", "--threads", "0"], "argument --threads: must be an integer in [1, 4,096] (or -1)"),
        (["--images", "{empty}", "--seed", "-1"], "argument --seed: must be an integer in [0,"),
        (["--images", "{empty}", "--seed", "2", "--threads", "4"], "--seed repeats a run only on one thread"),
    ],
)
def test_bad_input_is_one_line(tmp_path, capsys, args, message):
    (tmp_path / "empty").mkdir()
    args = [a.format(empty=tmp_path / "empty") for a in args]
    status, err = run_cli(["poses", *args, "--out", str(tmp_path / "capture")])
    assert status == 2 and message in error_line(err), err


def test_not_a_video_is_one_line(tmp_path):
    fake = tmp_path / "walk.mp4"
    fake.write_bytes(b"not a video")  # text: refused before ffmpeg runs, no frames folder made
    with pytest.raises(UserError, match=r"walk\.mp4: looks like text, expected a video file"):
        extract_frames(str(fake), str(tmp_path / "frames"), 2.0, progress=lambda _: None)
    assert not (tmp_path / "frames").exists()
    fake.write_bytes(np.random.default_rng(0).bytes(256))  # unrecognised bytes: ffmpeg's verdict
    with pytest.raises(UserError, match="not a video ffmpeg can read"):
        extract_frames(str(fake), str(tmp_path / "frames"), 2.0, progress=lambda _: None)
    with pytest.raises(MissingInputError):
        extract_frames(str(tmp_path / "missing.mp4"), str(tmp_path / "frames"), 2.0)


_CRASH = """
import faulthandler, sys, ctypes
faulthandler.enable()
if sys.argv[1] == "plain":
    import pycolmap
else:
    from llrmpp_jax.data.formats.colmap import import_pycolmap
    import_pycolmap()
ctypes.string_at(0)  # a segmentation fault
"""


@pytest.mark.parametrize("how", ["plain", "ours"])
def test_pycolmap_leaves_the_crash_handlers_alone(how):
    """A plain ``import pycolmap`` replaces the crash handlers with glog's (which can
    deadlock inside the C++ unwinder); ``import_pycolmap`` keeps the ones from before:
    a segfault afterwards is reported by Python's faulthandler and ends the process."""
    proc = subprocess.run([sys.executable, "-c", _CRASH, how], capture_output=True, text=True, timeout=120)
    assert proc.returncode == -signal.SIGSEGV, proc.stderr[-2000:]
    by_faulthandler = "Fatal Python error: Segmentation fault" in proc.stderr
    by_glog = "SIGSEGV (@0x0) received" in proc.stderr
    assert (by_faulthandler, by_glog) == ((False, True) if how == "plain" else (True, False)), proc.stderr[-2000:]


def test_too_few_photos_and_a_bad_fps_are_one_line(tmp_path, rng, capsys):
    """Two photos (poses need 3) and ``--fps 0`` on an existing file: one line each, exit 2,
    no model written."""
    two = tmp_path / "two"
    two.mkdir()
    for i in range(2):
        write_image(str(two / f"{i}.png"), rng.uniform(size=(32, 48, 3)).astype(np.float32))
    video = tmp_path / "walk.mp4"
    video.write_bytes(b"whatever")
    for args, message in (
        (["--images", str(two)], "2 images; poses need at least 3"),
        (["--video", str(video), "--fps", "0"], "argument --fps: must be a finite number > 0, got '0'"),
    ):
        out = tmp_path / f"capture_{args[0][2:]}"
        status, err = run_cli(["poses", *args, "--out", str(out)])
        assert status == 2 and message in error_line(err), err
        assert not (out / "sparse").exists()

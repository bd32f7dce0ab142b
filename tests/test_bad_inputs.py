"""A corpus of broken inputs, each run through ``llrmpp_jax.cli.main`` in this process: every
one ends in exit status 2 and one ``error:`` line naming the file or flag, what was found and
what was expected; nothing is written and nothing compiles (each is refused before).

The first three are the faults of issue 58 (a photo passed as a ``.gs``: numpy's traceback;
NaN Gaussians: ``render`` wrote frames while ``export`` refused; ``--frames 0``: a JAX
traceback); the rest come from ``tests/test_cli_fuzz.py``'s first runs and from reading the
loaders. ``tests/test_cli.py`` and ``tests/capture/test_cli.py`` keep the cases that need a
converted model or a reconstruction."""

from __future__ import annotations

import json
import os
import zipfile

import numpy as np
import pytest

from tests.helpers.bad_inputs import error_line, run_cli, tiny_capture, write_gs, write_photo

VIEWERS = ("render", "export", "refine", "view")  # every verb that reads a .gs file


def _gs_argv(verb: str, gs: str, out: str) -> list[str]:
    """``verb`` reading the .gs file ``gs``; its output (if any) goes to ``out``."""
    return {
        "render": ["render", "--gaussians", gs, "--path", "inputs", "--quiet", "--out", out],
        "export": ["export", "--gaussians", gs, "--ply", out + ".ply"],
        "refine": ["refine", "--checkpoint", "pretrained:small", "--gaussians", gs, "--out", out + ".gs"],
        "view": ["view", "--gaussians", gs, "--port", "0"],
    }[verb]


def _refused(tmp_path, argv: list[str], *parts: str) -> str:
    status, lines = run_cli(argv)
    assert status == 2, (argv, lines)
    line = error_line(lines)
    for p in parts:
        assert p in line, (argv, line)
    assert not [f for f in os.listdir(tmp_path) if f.startswith("out")], os.listdir(tmp_path)  # nothing written
    return line


@pytest.mark.parametrize("verb", VIEWERS)
def test_a_photo_given_as_a_gs_file_is_one_line(tmp_path, rng, verb):
    """Issue 58: numpy's 'pickled (object) data' traceback before the file was sniffed."""
    gs = write_photo(str(tmp_path / "scene.gs"), rng)
    line = _refused(tmp_path, _gs_argv(verb, gs, str(tmp_path / "out")), gs, "looks like a jpeg image", ".gs file")
    assert line.startswith("llrmpp: error: ")


@pytest.mark.parametrize("verb", VIEWERS)
def test_nan_gaussians_are_refused_by_every_command(tmp_path, rng, verb):
    """Issue 58: ``render`` of NaN means exited 0 and wrote frames while ``export`` refused."""
    n = 20
    gs = write_gs(str(tmp_path / "nan.gs"), rng, means=np.full((n, 3), np.nan, np.float32))
    _refused(tmp_path, _gs_argv(verb, gs, str(tmp_path / "out")), gs, "means has 60 non-finite value(s)")


def test_zero_frames_is_one_parser_line(tmp_path, rng):
    """Issue 58: ``render --path orbit --frames 0`` was a 30-line JAX traceback."""
    gs = write_gs(str(tmp_path / "ok.gs"), rng)
    argv = ["render", "--gaussians", gs, "--path", "orbit", "--frames", "0", "--out", str(tmp_path / "out")]
    _refused(tmp_path, argv, "argument --frames: must be an integer in [1, ", "got '0'")


def _gs_files(tmp_path, rng) -> dict[str, tuple[str, str]]:
    """``{case: (a broken .gs file, a part of its one line)}``."""
    d = tmp_path / "in"
    d.mkdir()
    ok = write_gs(str(d / "ok.gs"), rng)
    data = open(ok, "rb").read()
    cases = {}

    def put(name: str, content: bytes, expect: str) -> None:
        (d / name).write_bytes(content)
        cases[name] = (str(d / name), expect)

    put("cut.gs", data[: len(data) // 2], "looks like a truncated or damaged zip archive")
    put("empty.gs", b"", "looks like an empty file")
    put("text.gs", b"means = [1, 2, 3]\n", "looks like text")
    put("random.gs", np.random.default_rng(1).bytes(4096), "looks like binary data")
    put("npy.gs", open(_npy(d), "rb").read(), "looks like a NumPy .npy array")
    with zipfile.ZipFile(d / "zip.gs", "w") as z:
        z.writestr("readme.txt", "hello")
    cases["zip.gs"] = (str(d / "zip.gs"), "looks like a zip archive without header, means")
    n = 20
    for name, arrays, expect in (
        ("inf_scales.gs", {"scales": np.full((n, 3), np.inf, np.float32)}, "field scales has 60 non-finite"),
        ("nan_pose.gs", {"c2w": np.full((2, 4, 4), np.nan)}, "field c2w has 32 non-finite"),
        ("short_quats.gs", {"quats": np.ones((n - 1, 4), np.float32)}, "'quats' has shape (19, 4)"),
        ("flat_means.gs", {"means": np.ones(3 * n, np.float32)}, "'means' has shape (60,)"),
        ("bad_inputs.gs", {"inputs": np.array([5])}, "'inputs' must be frame indices in [0, 2)"),
        ("object_array.gs", {"features": np.array([{"a": 1}] * n, dtype=object)}, "truncated or corrupt .gs"),
        (
            "other_format.gs",
            {"header": np.frombuffer(json.dumps({"format": "x"}).encode(), np.uint8)},
            "not an llrmpp .gs file (format 'x')",
        ),
        ("list_header.gs", {"header": np.frombuffer(b"[1, 2]", np.uint8)}, "not an llrmpp .gs file"),
    ):
        cases[name] = (write_gs(str(d / name), rng, **arrays), expect)
    return cases


def _npy(d) -> str:
    np.save(d / "a.npy", np.zeros(3))
    return str(d / "a.npy")


@pytest.mark.parametrize("verb", ("render", "export"))
def test_broken_gs_files_are_one_line(tmp_path, rng, verb):
    for name, (gs, expect) in _gs_files(tmp_path, rng).items():
        line = _refused(tmp_path, _gs_argv(verb, gs, str(tmp_path / "out")), gs)
        assert expect in line, (name, line)


# flag values the parser refuses: (argv, the start of what the error line says after "argument FLAG: ")
_GS = "{gs}"
PARSER_CASES = [
    (["render", "--gaussians", _GS, "--frames", "-3"], "--frames: must be an integer in [1, 1,000,000]"),
    (["render", "--gaussians", _GS, "--frames", "1e3"], "--frames: must be an integer"),
    (["render", "--gaussians", _GS, "--frames", "9" * 5000], "--frames: must be an integer"),
    (["render", "--gaussians", _GS, "--fps", "nan"], "--fps: must be a finite number > 0"),
    (["render", "--gaussians", _GS, "--fps", "0"], "--fps: must be a finite number > 0"),
    (["render", "--gaussians", _GS, "--fps", "inf"], "--fps: must be a finite number > 0"),
    (["render", "--scene", "x", "--size", "0"], "--size: must be H or HxW"),
    (["render", "--scene", "x", "--size", "256x-8"], "--size: must be H or HxW"),
    (["render", "--scene", "x", "--size", ""], "--size: must be H or HxW"),
    (["render", "--scene", "x", "--size", "99999"], "--size: must be H or HxW"),
    (["render", "--scene", "x", "--num-inputs", "0"], "--num-inputs: must be an integer in [1, "),
    (["render", "--scene", "x", "--inputs", "1,-2"], "--inputs: must be comma-separated frame indices >= 0"),
    (["render", "--scene", "x", "--inputs", ","], "--inputs: must be comma-separated frame indices"),
    (["render", "--scene", "x", "--repeats", "0"], "--repeats: must be an integer in [1, "),
    (["reconstruct", "--scene", "x", "--checkpoint", "c", "--out", "o", "--fps", "-1"], "--fps: must be a finite"),
    (["reconstruct", "--scene", "x", "--checkpoint", "c", "--out", "o", "--threads", "0"], "--threads: must be an"),
    (["poses", "--images", "x", "--out", "o", "--max-image-size", "8"], "--max-image-size: must be an integer in [64,"),
    (["poses", "--images", "x", "--out", "o", "--seed", "-1"], "--seed: must be an integer in [0, "),
    (
        ["poses", "--images", "x", "--out", "o", "--threads", "-2"],
        "--threads: must be an integer in [1, 4,096] (or -1)",
    ),
    (["export", "--gaussians", _GS, "--ply", "o", "--sh-degree", "4"], "--sh-degree: must be an integer in [0, 3]"),
    (["export", "--gaussians", _GS, "--ply", "o", "--bake-steps", "0"], "--bake-steps: must be an integer in [1,"),
    (["export", "--gaussians", _GS, "--ply", "o", "--bake-views-per-step", "0"], "--bake-views-per-step: must be"),
    (["export", "--gaussians", _GS, "--ply", "o", "--bake-views-between", "-1"], "--bake-views-between: must be"),
    (["refine", "--checkpoint", "c", "--gaussians", _GS, "--out", "o", "--steps", "0"], "--steps: must be an integer"),
    (["refine", "--checkpoint", "c", "--gaussians", _GS, "--out", "o", "--views-per-step", "0"], "--views-per-step:"),
    (["refine", "--checkpoint", "c", "--gaussians", _GS, "--out", "o", "--perceptual-weight", "-1"], "--perceptual-w"),
    (["refine", "--checkpoint", "c", "--gaussians", _GS, "--out", "o", "--perceptual-weight", "nan"], "--perceptual-w"),
    (["eval", "--config", "demo", "--checkpoint", "c", "--out", "o", "--refine-steps", "-1"], "--refine-steps: must"),
    (
        ["eval", "--config", "demo", "--checkpoint", "c", "--out", "o", "--refine-perceptual-weight", "-0.5"],
        "--refine-p",
    ),
    (["eval", "--config", "demo", "--checkpoint", "c", "--out", "o", "--size", "big"], "--size: must be H or HxW"),
    (["eval", "--config", "demo", "--checkpoint", "c", "--out", "o", "--max-scenes", "0"], "--max-scenes: must be"),
    (["eval", "--config", "demo", "--checkpoint", "c", "--out", "o", "--num-inputs", "-1"], "--num-inputs: must be"),
    (
        ["train", "--config", "demo", "--workdir", "o", "--max-minutes", "0"],
        "--max-minutes: must be a finite number > 0",
    ),
    (["train", "--config", "demo", "--workdir", "o", "--heartbeat-timeout", "0"], "--heartbeat-timeout: must be"),
    (["demo", "--out", "o", "--steps", "0"], "--steps: must be an integer in [1, "),
    (["demo", "--out", "o", "--minutes=-inf"], "--minutes: must be a finite number > 0"),
    (["bench", "--scale", "cpu", "--out", "o", "--views", "0,16"], "--views: must be comma-separated view counts"),
    (["bench", "--scale", "cpu", "--out", "o", "--size", "544"], "--size: must be HxW"),
    (["view", "--gaussians", _GS, "--port", "99999"], "--port: must be an integer in [0, 65,535]"),
    (["view", "--gaussians", _GS, "--height", "0"], "--height: must be an integer in [1, 16,384]"),
    (["view", "--gaussians", _GS, "--moving-height", "x"], "--moving-height: must be an integer"),
    (["view", "--procedural", "-1"], "--procedural: must be an integer in [0, "),
    # argparse turns a value "--" into [] (found by the fuzz): refused before any command sees it
    (["plan", "--programs=--"], "--programs: expected a value, got '--'"),
    (["render", "--gaussians", _GS, "--path=--", "--out", "o"], "--path: expected a value, got '--'"),
]


@pytest.mark.parametrize("argv, says", PARSER_CASES, ids=lambda v: " ".join(v)[:60] if isinstance(v, list) else None)
def test_out_of_range_numbers_are_refused_by_the_parser(tmp_path, rng, argv, says):
    gs = write_gs(str(tmp_path / "ok.gs"), rng)
    argv = [a.replace(_GS, gs) for a in argv]
    argv = [str(tmp_path / "out") if a == "o" else a for a in argv]
    line = _refused(tmp_path, argv, f"argument {says}")
    assert line.startswith(f"llrmpp {argv[0]}: error: argument "), line


def test_files_that_are_not_what_their_flag_says(tmp_path, rng):
    """A photo as a torch checkpoint, a photo as a checkpoint folder, text as a video, a
    params folder whose metadata is not JSON, a PLY that is not one or holds NaN."""
    from llrmpp_jax.errors import UserError
    from llrmpp_jax.export_ply import export_ply, read_ply
    from tests.helpers.bad_inputs import tiny_saved_scene

    photo = write_photo(str(tmp_path / "weights.pt"), rng)
    out = str(tmp_path / "out")
    _refused(tmp_path, ["convert", "--checkpoint", photo, "--out", out], photo, "looks like a jpeg image")
    _refused(
        tmp_path,
        ["eval", "--config", "demo", "--checkpoint", photo, "--out", out],
        photo,
        "looks like a jpeg image, expected a checkpoint folder",
    )
    video = tmp_path / "walk.mp4"
    video.write_text("this is not a video\n")
    _refused(tmp_path, ["poses", "--video", str(video), "--out", out], str(video), "looks like text, expected a video")
    params = tmp_path / "params"
    params.mkdir()
    (params / "llrmpp_params.json").write_bytes(b"\x00\x01 not json")
    _refused(
        tmp_path,
        ["eval", "--config", "demo", "--checkpoint", str(params), "--out", out],
        f"{params}: a params folder without its orbax checkpoint",
    )
    from llrmpp_jax.params_io import load_params

    with pytest.raises(UserError, match=r"llrmpp_params\.json: looks like binary data .*, expected the params"):
        load_params(str(params))
    not_ply = write_photo(str(tmp_path / "cloud.ply"), rng)
    with pytest.raises(UserError, match=r"cloud\.ply: looks like a jpeg image, expected a PLY file"):
        read_ply(not_ply)
    saved = tiny_saved_scene(rng)
    ply = str(tmp_path / "nan.ply")
    export_ply(ply, saved.gaussians, saved.model, saved.world_from_scene)
    text = open(ply, "rb").read()
    body = np.frombuffer(text[text.index(b"end_header\n") + 11 :], np.float32).copy()
    body[::7] = np.nan
    open(ply, "wb").write(text[: text.index(b"end_header\n") + 11] + body.tobytes())
    with pytest.raises(UserError, match=r"nan\.ply: property \w+ has \d+ non-finite value"):
        read_ply(ply)
    with open(ply, "r+b") as f:
        f.truncate(len(text) // 2)
    with pytest.raises(UserError, match=r"nan\.ply: truncated or corrupt PLY file"):
        read_ply(ply)


def test_what_the_fuzzing_found_in_captures(tmp_path, rng):
    """tests/test_cli_fuzz.py's first runs: a transforms.json that is not UTF-8 (a
    UnicodeDecodeError traceback) or not a JSON object (an AttributeError traceback); a
    capture frame cut short (OpenImageIO's two-line message); a photo folder holding a text
    file named .jpg (the error named the copy in --out and left --out/images behind)."""
    reconstruct = ["reconstruct", "--checkpoint", "pretrained:small", "--num-inputs", "2", "--out"]
    out = str(tmp_path / "out.gs")
    for name, content, says in (
        ("latin1", b"\x80", "looks like binary data (starts 80), expected a nerfstudio transforms file"),
        ("null", b"null", "expected a JSON object with a 'frames' list, got NoneType"),
        ("list", b"[1, 2]", "expected a JSON object with a 'frames' list, got list"),
    ):
        capture = tiny_capture(str(tmp_path / f"in_{name}"), rng)
        (tmp_path / f"in_{name}" / "transforms.json").write_bytes(content)
        _refused(tmp_path, [*reconstruct, out, "--scene", capture], "transforms.json", says)
    capture = tiny_capture(str(tmp_path / "in_cut"), rng, image_ext=".jpg")
    frame = sorted(os.listdir(tmp_path / "in_cut" / "images"))[1]
    data = (tmp_path / "in_cut" / "images" / frame).read_bytes()
    (tmp_path / "in_cut" / "images" / frame).write_bytes(data[:200])
    _refused(tmp_path, [*reconstruct, out, "--scene", capture], frame)
    photos = tmp_path / "in_photos"
    photos.mkdir()
    for i in range(3):
        write_photo(str(photos / f"{i}.jpg"), rng)
    (photos / "1.jpg").write_text("not a photo\n")
    _refused(
        tmp_path,
        ["poses", "--images", str(photos), "--out", str(tmp_path / "out_capture")],
        f"cannot open image file {photos / '1.jpg'}",
        "it looks like text",
    )


@pytest.mark.parametrize("verb", ("eval", "reconstruct"))
def test_a_nan_pose_in_a_capture_is_refused_by_eval_and_reconstruct(tmp_path, rng, verb):
    """The capture's cameras are checked where they are read: the same line (file, frame,
    field, how many values) from both commands, before any weights load."""
    capture = tiny_capture(str(tmp_path / "in_capture"), rng)
    meta = json.load(open(tmp_path / "in_capture" / "transforms.json"))
    meta["frames"][2]["transform_matrix"][0][3] = float("nan")
    json.dump(meta, open(tmp_path / "in_capture" / "transforms.json", "w"))
    out = str(tmp_path / "out")
    argv = {
        "eval": ["eval", "--config", "small", "--checkpoint", "pretrained:small", "--data", capture, "--out", out],
        "reconstruct": ["reconstruct", "--scene", capture, "--checkpoint", "pretrained:small", "--out", out],
    }[verb]
    _refused(
        tmp_path, argv, "transforms.json, frame 2", "has non-finite values (1 non-finite value(s) in 1 of 6 frames)"
    )

"""Your own capture from the command line: convert -> reconstruct -> render -> export, the
golden Long-LRM Gaussians through the CLI, fox (nerfstudio) and beer (COLMAP) end to end,
and every bad input as one line with exit status 2."""

import json
import os
import re

import imageio_ffmpeg
import jax.numpy as jnp
import numpy as np
import pytest

from llrmpp_jax.capture import load_gs, save_gs
from llrmpp_jax.cli import main
from llrmpp_jax.data import in_memory_scene
from llrmpp_jax.data.formats import write_colmap_scene, write_nerfstudio_scene
from llrmpp_jax.data.image_io import read_image
from llrmpp_jax.export_ply import read_ply, standard_fields
from llrmpp_jax.model import render
from tests.helpers.environment import GOLDEN, ROOT, shared_path
from tests.helpers.photos import fox_video

FOX, BEER = shared_path("data", "fox"), shared_path("data", "beer")


def _rel_err(got, want) -> float:
    return float(np.max(np.abs(np.asarray(got, np.float64) - want)) / np.max(np.abs(want)))


@pytest.fixture(scope="module")
def golden(tmp_path_factory):
    """The golden tiny Long-LRM converted by ``llrmpp convert``: ``(params_dir, exp_file)``."""
    d = tmp_path_factory.mktemp("golden")
    exp = d / "golden_exp.py"
    exp.write_text(
        f"import sys\nsys.path.insert(0, {ROOT!r})\n" + "from tests.helpers.golden import golden_model_config\n"
        "from llrmpp_jax.experiment import ExperimentConfig, StageConfig\n"
        "def get_config():\n"
        "    return ExperimentConfig(name='golden', model=golden_model_config(), stages=(\n"
        "        StageConfig('s', steps=1, global_batch=2, num_inputs=2, num_targets=1, resize_h=32),))\n"
    )
    out = d / "params"
    assert (
        main(
            ["convert", "--checkpoint", os.path.join(GOLDEN, "state_dict.npz"), "--config", str(exp), "--out", str(out)]
        )
        == 0
    )
    return str(out), str(exp)


@pytest.mark.slow
def test_golden_through_the_cli(golden, tmp_path):
    """convert -> reconstruct (golden inputs, capture frame kept) equals the official
    Gaussians to 1e-4 relative (float32); render --gaussians equals model.render called
    directly, to the 8-bit PNG's rounding (0.5/255); render --scene gives the same PNGs."""
    params_dir, _ = golden
    inp = np.load(os.path.join(GOLDEN, "inputs.npz"))
    out = np.load(os.path.join(GOLDEN, "outputs.npz"))
    images = inp["images"][0].transpose(0, 2, 3, 1)
    scene = in_memory_scene(
        "golden", images, inp["c2ws"][0].astype(np.float64), inp["intrinsics"][0].astype(np.float64)
    )
    write_nerfstudio_scene(scene, str(tmp_path / "scene"), image_ext=".exr")  # float EXR: lossless inputs
    gs = str(tmp_path / "g.gs")
    assert (
        main(
            [
                "reconstruct",
                "--checkpoint",
                params_dir,
                "--scene",
                str(tmp_path / "scene"),
                "--inputs",
                "0,1",
                "--size",
                "32x48",
                "--no-normalize",
                "--repeats",
                "1",
                "--out",
                gs,
            ]
        )
        == 0
    )
    saved = load_gs(gs)
    g = saved.gaussians
    assert _rel_err(g.means, out["xyz"][0]) < 1e-4
    assert _rel_err(g.features, out["feature"][0].reshape(3072, 48)) < 1e-4
    assert _rel_err(g.scales, out["render_scales"][0]) < 1e-4
    assert _rel_err(g.quats, out["render_quats"][0]) < 1e-4
    assert _rel_err(g.opacities, out["render_opacities"][0]) < 1e-4

    assert main(["render", "--gaussians", gs, "--path", "inputs", "--quiet", "--out", str(tmp_path / "f")]) == 0
    want = render(
        {},
        saved.model,
        type(g)(*(jnp.asarray(x)[None] for x in g)),
        jnp.asarray(saved.c2w[None], jnp.float32),
        jnp.asarray(saved.intrinsics[None], jnp.float32),
        32,
        48,
    ).images["rgb"][0]
    for i, name in enumerate(("frame_00000", "frame_00001")):
        got = read_image(str(tmp_path / "f" / f"{name}.png"))
        assert np.max(np.abs(got - np.clip(np.asarray(want[i]), 0, 1))) <= 0.5 / 255 + 1e-6
    # straight from the capture: the same frames
    assert (
        main(
            [
                "render",
                "--scene",
                str(tmp_path / "scene"),
                "--checkpoint",
                params_dir,
                "--inputs",
                "0,1",
                "--size",
                "32x48",
                "--no-normalize",
                "--repeats",
                "1",
                "--path",
                "inputs",
                "--quiet",
                "--out",
                str(tmp_path / "direct"),
            ]
        )
        == 0
    )
    for name in ("frame_00000", "frame_00001"):
        np.testing.assert_array_equal(
            read_image(str(tmp_path / "direct" / f"{name}.png")), read_image(str(tmp_path / "f" / f"{name}.png"))
        )


@pytest.mark.slow
@pytest.mark.parametrize("capture", [FOX, BEER], ids=["fox_nerfstudio", "beer_colmap"])
def test_capture_end_to_end(golden, capture, tmp_path, capsys):
    """reconstruct -> render targets (metrics, frames named after the photos) -> spline
    video (decodes to --frames frames) + depth EXR -> export PLY (standard 3DGS fields) ->
    refine with the perceptual term (prints held-out PSNR before/after; the input-view loss
    falls; a negative weight is one line)."""
    params_dir, _ = golden
    gs = str(tmp_path / "s.gs")
    assert (
        main(
            [
                "reconstruct",
                "--checkpoint",
                params_dir,
                "--scene",
                capture,
                "--num-inputs",
                "4",
                "--size",
                "64",
                "--repeats",
                "3",
                "--timing",
                str(tmp_path / "t.json"),
                "--out",
                gs,
            ]
        )
        == 0
    )
    report = capsys.readouterr().out
    assert "inputs (4)" in report and "held-out targets" in report and "median of 3 synced runs" in report
    saved = load_gs(gs)
    h, w = saved.image_hw
    assert (h, w) == (64, 32)  # both captures are portrait: the aspect is kept
    timing = json.load(open(tmp_path / "t.json"))
    assert len(timing["runs_s"]) == 3 and timing["run_s"] == pytest.approx(np.median(timing["runs_s"]))

    frames = tmp_path / "targets"
    assert main(["render", "--gaussians", gs, "--path", "targets", "--quiet", "--out", str(frames)]) == 0
    stems = sorted(os.path.splitext(os.path.basename(saved.frame_names[i]))[0] for i in saved.targets)
    assert sorted(f[:-4] for f in os.listdir(frames) if f.endswith(".png")) == stems
    metrics = json.load(open(frames / "metrics.json"))
    assert len(metrics["per_view"]) == len(stems) and np.isfinite(metrics["mean"]["psnr"])

    video = str(tmp_path / "path.mp4")
    assert (
        main(
            [
                "render",
                "--gaussians",
                gs,
                "--path",
                "spline",
                "--frames",
                "7",
                "--video",
                video,
                "--fps",
                "10",
                "--depth",
                "--quiet",
                "--out",
                str(tmp_path / "spline"),
            ]
        )
        == 0
    )
    reader = imageio_ffmpeg.read_frames(video)
    meta = next(reader)
    assert tuple(meta["size"]) == (w, h) and sum(1 for _ in reader) == 7
    assert len([f for f in os.listdir(tmp_path / "spline") if f.endswith("_depth.exr")]) == 7

    ply = str(tmp_path / "s.ply")
    assert main(["export", "--gaussians", gs, "--ply", ply]) == 0
    back = read_ply(ply)
    assert back.mode == "color" and back.gaussians.means.shape == saved.gaussians.means.shape
    import plyfile

    assert list(plyfile.PlyData.read(ply)["vertex"].data.dtype.names) == standard_fields(3)

    capsys.readouterr()
    refined = str(tmp_path / "r.gs")
    assert (
        main(
            [
                "refine",
                "--checkpoint",
                params_dir,
                "--gaussians",
                gs,
                "--scene",
                capture,
                "--steps",
                "3",
                "--perceptual-weight",
                "0.5",
                "--quiet",
                "--out",
                refined,
            ]
        )
        == 0
    )
    out = capsys.readouterr().out
    before, after = (float(re.search(rf"PSNR {w} (\d+\.\d\d)\n", out).group(1)) for w in ("before", "after"))  # pyright: ignore[reportOptionalMemberAccess] -- the command prints these lines; a miss fails the test either way
    loss0, loss1 = (
        float(v)
        for v in re.search(r"input-view loss (\S+) -> (\S+) \(the first step's views\);", out).groups()  # pyright: ignore[reportOptionalMemberAccess] -- as above
    )
    assert np.isfinite([before, after]).all() and loss1 < loss0  # 3 steps lower the loss on the inputs
    assert load_gs(refined).gaussians.means.shape == saved.gaussians.means.shape
    # --steps 0, --views-per-step 0, a negative weight: the parser's (tests/test_bad_inputs.py)
    for flags, line in ((["--views-per-step", "5"], "--views-per-step must be in [1, 4] (the input views), got 5"),):
        assert main(["refine", "--checkpoint", params_dir, "--gaussians", gs, *flags, "--out", refined]) == 2
        assert capsys.readouterr().err.strip().splitlines() == [f"llrmpp: error: {line}"]


def _tiny_scene(tmp_path, n=6, h=32, w=48):
    rng = np.random.default_rng(0)
    c2w = np.tile(np.eye(4), (n, 1, 1))
    c2w[:, 0, 3] = np.linspace(-1, 1, n)
    k = np.tile([[40.0, 40.0, w / 2, h / 2]], (n, 1))
    scene = in_memory_scene("t", rng.uniform(0.1, 0.9, (n, h, w, 3)), c2w, k)
    write_nerfstudio_scene(scene, str(tmp_path / "ns"), image_ext=".png", bits=8)
    return str(tmp_path / "ns")


def _edit_transforms(folder, fn):
    path = os.path.join(folder, "transforms.json")
    data = json.load(open(path))
    fn(data)
    json.dump(data, open(path, "w"))


def _bad_cases(tmp_path, golden):
    params_dir, exp = golden
    ns = _tiny_scene(tmp_path)
    cases = {}
    empty = tmp_path / "empty"
    empty.mkdir()
    cases["unknown format"] = (["--scene", str(empty)], "no known scene format (looked for transforms.json")
    colmap = tmp_path / "colmap"
    sparse = write_colmap_scene(
        in_memory_scene(
            "c", np.full((2, 16, 16, 3), 0.5), np.tile(np.eye(4), (2, 1, 1)), np.tile([[20.0, 20, 8, 8]], (2, 1))
        ),
        str(colmap),
    )
    os.remove(os.path.join(sparse, "images.bin"))
    cases["colmap without images"] = (["--scene", str(colmap)], "has cameras but no images.bin or images.txt")
    nan = tmp_path / "nan"
    os.system(f"cp -r {ns} {nan}")
    _edit_transforms(nan, lambda d: d["frames"][2]["transform_matrix"][0].__setitem__(3, float("nan")))
    cases["NaN pose"] = (["--scene", str(nan)], "frame 2 (")
    skew = tmp_path / "skew"
    os.system(f"cp -r {ns} {skew}")
    _edit_transforms(skew, lambda d: d["frames"][3]["transform_matrix"][0].__setitem__(0, 2.0))
    cases["non-rotation pose"] = (["--scene", str(skew)], "is not a rotation")
    corrupt = tmp_path / "corrupt"
    os.system(f"cp -r {ns} {corrupt}")
    with open(corrupt / "images" / "frame_00001.png", "r+b") as f:
        f.seek(60)
        f.write(b"\x00" * 200)
    cases["corrupt input image"] = (["--scene", str(corrupt)], "frame_00001.png")
    cases["inputs out of range"] = (["--scene", ns, "--inputs", "1,9"], "--inputs: index 9 is out of range")
    cases["size not a multiple"] = (["--scene", ns, "--size", "40"], "--size: height 40 is not a positive multiple of")
    cases["too few frames"] = (["--scene", ns, "--num-inputs", "6"], "fewer than the 6 inputs requested")
    cases["another architecture"] = (["--scene", ns, "--config", "demo"], "first mismatch")
    return ns, params_dir, cases


def test_bad_inputs_are_one_line_before_compiling(golden, tmp_path, capsys):
    ns, params_dir, cases = _bad_cases(tmp_path, golden)
    for what, (args, message) in cases.items():
        rc = main(
            ["reconstruct", "--checkpoint", params_dir, "--num-inputs", "2", *args, "--out", str(tmp_path / "x.gs")]
        )
        captured = capsys.readouterr()
        lines = captured.err.strip().splitlines()
        assert rc == 2 and len(lines) == 1 and message in lines[0], (what, captured.err)
        assert "compile" not in captured.out, what  # failed before the model compiled


def test_gs_file_version_and_truncation(golden, tmp_path, capsys):
    """A .gs of another version, or cut short, is refused in one line naming the file."""
    params_dir, _ = golden
    ns = _tiny_scene(tmp_path)
    gs = str(tmp_path / "ok.gs")
    assert (
        main(
            [
                "reconstruct",
                "--checkpoint",
                params_dir,
                "--scene",
                ns,
                "--num-inputs",
                "2",
                "--size",
                "32",
                "--repeats",
                "1",
                "--out",
                gs,
            ]
        )
        == 0
    )
    saved = load_gs(gs)
    data = open(gs, "rb").read()
    with open(tmp_path / "cut.gs", "wb") as f:
        f.write(data[: len(data) // 2])
    import llrmpp_jax.capture.scene_file as SF

    old = SF.GS_VERSION
    try:
        SF.GS_VERSION = 99
        save_gs(str(tmp_path / "v99.gs"), saved)
    finally:
        SF.GS_VERSION = old
    capsys.readouterr()
    for name, message in (
        ("cut.gs", "looks like a truncated or damaged zip archive, expected an llrmpp .gs file"),
        ("v99.gs", ".gs version 99, this llrmpp reads version 1"),
    ):
        rc = main(["render", "--gaussians", str(tmp_path / name), "--out", str(tmp_path / "r")])
        err = capsys.readouterr().err.strip().splitlines()
        assert rc == 2 and len(err) == 1 and name in err[0] and message in err[0], err


def test_convert_lists_unused_keys(tmp_path, golden, capsys):
    """Keys outside the model are counted and refused; --allow-unused converts anyway and
    the params folder loads back with its recorded config."""
    _, exp = golden
    sd = dict(np.load(os.path.join(GOLDEN, "state_dict.npz")))
    sd["perceptual.vgg.0.weight"] = np.ones(3, np.float32)
    sd["ema.tokenizer.weight"] = np.ones(3, np.float32)
    np.savez(tmp_path / "extra.npz", **sd)
    args = ["convert", "--checkpoint", str(tmp_path / "extra.npz"), "--config", exp, "--out", str(tmp_path / "p")]
    assert main(args) == 2
    err = capsys.readouterr().err
    assert "2 key(s) outside the model's prefixes" in err and "--allow-unused" in err
    assert main([*args, "--allow-unused"]) == 0
    assert "ignored 2 key(s)" in capsys.readouterr().out
    from llrmpp_jax.params_io import load_params

    params, cfg = load_params(str(tmp_path / "p"))
    assert cfg.head.mode == "color"
    want = np.load(os.path.join(GOLDEN, "state_dict.npz"))["tokenDecoder.1.weight"].T
    np.testing.assert_array_equal(np.asarray(params["head"]["proj"]["kernel"]), want)


def test_reconstruct_from_a_video_end_to_end(golden, tmp_path, capsys):
    """``reconstruct --video``: frames, poses (COLMAP, sequential matching for a video), the
    model, a ``.gs`` file; then a held-out frame rendered with its metrics."""
    params_dir, _ = golden
    video = str(tmp_path / "walk.mp4")
    frames = fox_video(video, size=320, fps=5)
    gs = str(tmp_path / "walk.gs")
    assert (
        main(
            [
                "reconstruct",
                "--video",
                video,
                "--fps",
                "5",
                "--max-image-size",
                "320",
                "--checkpoint",
                params_dir,
                "--num-inputs",
                "4",
                "--size",
                "64",
                "--out",
                gs,
            ]
        )
        == 0
    )
    out = capsys.readouterr().out
    assert "matching: sequential" in out and f"of {frames} images" in out, out
    capture = tmp_path / "walk_capture"
    assert sorted(os.listdir(capture / "images")) == [f"frame_{i:05d}.jpg" for i in range(frames)]
    saved = load_gs(gs)
    assert len(saved.inputs) == 4 and len(saved.targets) >= 1 and saved.image_hw[0] == 64
    rendered = tmp_path / "targets"
    assert main(["render", "--gaussians", gs, "--path", "targets", "--quiet", "--out", str(rendered)]) == 0
    pngs = [f for f in os.listdir(rendered) if f.endswith(".png")]
    assert len(pngs) == len(saved.targets) and read_image(str(rendered / pngs[0])).shape[:2] == saved.image_hw
    assert np.isfinite(json.load(open(rendered / "metrics.json"))["mean"]["psnr"])

"""Baking feature Gaussians into standard colour Gaussians (``llrmpp export --bake``):
the colour initialisation against a per-Gaussian loop, the fit through the command line on
a procedural capture (the standard 3DGS PLY layout; renders close to the model's on views
the fit never saw), and bad input as one line."""

from __future__ import annotations

import dataclasses
import re

import numpy as np
import plyfile
import pytest

from llrmpp_jax.capture import load_gs
from llrmpp_jax.capture.bake import BakeConfig, bake_colour, colour_config, initial_colours
from llrmpp_jax.cli import main
from llrmpp_jax.data.formats import write_nerfstudio_scene
from llrmpp_jax.data.synthetic import ProceduralConfig, procedural_scene
from llrmpp_jax.errors import UserError
from llrmpp_jax.export_ply import read_ply


def test_initial_colours_match_a_per_gaussian_loop(rng):
    v, n, h, w = 3, 200, 12, 16
    c2w = np.tile(np.eye(4), (v, 1, 1))
    c2w[:, :3, 3] = rng.normal(scale=0.2, size=(v, 3))
    intr = np.array([[14.0, 13.0, 8.0, 6.0]] * v) + rng.uniform(-1, 1, size=(v, 4))
    means = rng.normal(size=(n, 3)) * [1.0, 1.0, 0.5] + [0.0, 0.0, 1.5]
    means[:5, 2] = -1.0  # behind every camera
    images = rng.uniform(size=(v, h, w, 3))
    got = initial_colours(means, c2w, intr, images)
    for i in range(n):
        seen = []
        for k in range(v):
            x, y, z = np.linalg.inv(c2w[k])[:3] @ np.append(means[i], 1.0)
            if z <= 0:
                continue
            u, vv = intr[k, 0] * x / z + intr[k, 2], intr[k, 1] * y / z + intr[k, 3]
            if 0 <= u < w and 0 <= vv < h:
                seen.append(images[k, int(vv), int(u)])
        want = np.mean(seen, axis=0) if seen else np.full(3, 0.5)
        np.testing.assert_allclose(got[i], want, atol=1e-12)
    assert np.all(got[:5] == 0.5)


@pytest.fixture(scope="module")
def feature_scene(tmp_path_factory):
    """A procedural capture reconstructed by the shipped feature-mode model at 64 px."""
    d = tmp_path_factory.mktemp("bake")
    scene = procedural_scene(3, ProceduralConfig(height=64, width=64, num_frames=12))
    write_nerfstudio_scene(scene, str(d / "capture"))
    gs = str(d / "scene.gs")
    assert (
        main(
            [
                "reconstruct",
                "--checkpoint",
                "pretrained:small",
                "--scene",
                str(d / "capture"),
                "--num-inputs",
                "6",
                "--size",
                "64",
                "--repeats",
                "1",
                "--out",
                gs,
            ]
        )
        == 0
    )
    return gs


def test_export_bake_writes_the_standard_layout_close_to_the_model(feature_scene, tmp_path, capsys):
    ply = str(tmp_path / "baked.ply")
    capsys.readouterr()
    assert (
        main(
            [
                "export",
                "--gaussians",
                feature_scene,
                "--checkpoint",
                "pretrained:small",
                "--ply",
                ply,
                "--bake",
                "--bake-steps",
                "100",
            ]
        )
        == 0
    )
    out = capsys.readouterr().out
    fitted = re.search(r"fitted views ([\d.]+) -> ([\d.]+) dB", out)
    held_out = re.search(r"baked vs the model's renders ([\d.]+) dB", out)
    photos = re.search(r"held-out photos: baked ([\d.]+) dB, the model ([\d.]+) dB", out)
    assert fitted and held_out and photos, out
    assert float(fitted[2]) > float(fitted[1]) + 8.0, out
    # Views the fit never saw: the baked Gaussians render like the model (~20 dB at 200 updates).
    assert float(held_out[1]) > 17.0, out
    vertex = plyfile.PlyData.read(ply)["vertex"].data
    # 3DGS's own layout (its PLY writer's field order), as every viewer reads it.
    assert list(vertex.dtype.names) == (
        ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
        + [f"f_rest_{i}" for i in range(45)]
        + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    )
    assert len(vertex) == load_gs(feature_scene).gaussians.means.shape[0]
    assert read_ply(ply).mode == "color"


def test_bad_bake_input_is_one_line(feature_scene, tmp_path, capsys):
    capsys.readouterr()
    # --sh-degree 4: the parser's (tests/test_bad_inputs.py); BakeConfig's own check:
    with pytest.raises(UserError, match=r"--sh-degree must be in 0\.\.3, got 4"):
        BakeConfig(sh_degree=4)
    assert main(["export", "--gaussians", feature_scene, "--ply", str(tmp_path / "x.ply"), "--bake"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "needs --checkpoint" in err[0], err
    saved = load_gs(feature_scene)
    with pytest.raises(UserError, match="already in colour mode"):
        bake_colour({}, dataclasses.replace(saved, model=colour_config(saved.model, 3)), BakeConfig())

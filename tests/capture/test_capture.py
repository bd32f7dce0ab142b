"""The capture library: format detection for every reader, view selection, view sizes,
camera paths (spline through the inputs, orbit around their look-at point), the ``.gs``
file and params folders."""

import os
from dataclasses import replace

import jax
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from llrmpp_jax import config as C
from llrmpp_jax.capture import SavedScene, load_gs, save_gs, select_views
from llrmpp_jax.capture.reconstruct import view_size
from llrmpp_jax.capture.render import orbit_path, spline_path
from llrmpp_jax.data.formats import (
    dataset_scenes,
    detect_format,
    read_scene,
    write_colmap_scene,
    write_long_lrm_scene,
    write_nerfstudio_scene,
    write_re10k_scene,
    write_scannet_scene,
)
from llrmpp_jax.data.scene import in_memory_scene
from llrmpp_jax.data.synthetic import ProceduralConfig, procedural_scene
from llrmpp_jax.gaussians import Gaussians
from llrmpp_jax.geometry import validate_cameras
from llrmpp_jax.model import check_params_fit, init_params
from llrmpp_jax.params_io import load_params, save_params


@pytest.fixture(scope="module")
def source():
    s = procedural_scene(3, ProceduralConfig(height=16, width=24, num_frames=3))
    images = np.stack([s.image(i) for i in range(3)])
    depth = np.stack([s.depth(i) for i in range(3)])
    return in_memory_scene("det", images, s.c2w, s.intrinsics, depth)


@pytest.mark.parametrize("kind", ["nerfstudio", "colmap_bin", "colmap_txt", "scannet", "long_lrm", "re10k"])
def test_read_scene_detects_every_format(tmp_path, source, kind):
    """Each writer's output is detected as its own format and read back with the same cameras."""
    out = str(tmp_path / "scene")
    if kind == "nerfstudio":
        write_nerfstudio_scene(source, out)
        path, want = out, "nerfstudio"
    elif kind.startswith("colmap"):
        write_colmap_scene(source, out, binary=kind == "colmap_bin")
        path, want = out, "colmap"
    elif kind == "scannet":
        write_scannet_scene(source, out)
        path, want = out, "scannet"
    elif kind == "long_lrm":
        path, want = write_long_lrm_scene(source, out), "long_lrm"
    else:
        path, want = write_re10k_scene(source, out), "re10k"
    assert detect_format(path) == want
    scene = read_scene(path)
    np.testing.assert_allclose(scene.c2w, source.c2w, atol=1e-6)
    assert dataset_scenes(path) == [path]


def test_dataset_root_lists_its_scenes(tmp_path, source):
    write_nerfstudio_scene(source, str(tmp_path / "root" / "a"))
    write_colmap_scene(source, str(tmp_path / "root" / "b"))
    paths = dataset_scenes(str(tmp_path / "root"))
    assert [os.path.basename(p) for p in paths] == ["a", "b"]
    assert [len(read_scene(p)) for p in paths] == [3, 3]  # each detected on its own


def test_unknown_folder_lists_what_was_looked_for(tmp_path):
    with pytest.raises(ValueError, match=r"no known scene format \(looked for transforms.json .*\(COLMAP\)"):
        read_scene(str(tmp_path))


def _line_scene(n: int):
    c2w = np.tile(np.eye(4), (n, 1, 1))
    c2w[:, 0, 3] = np.arange(n, dtype=np.float64)
    return in_memory_scene("line", np.full((n, 32, 16, 3), 0.5), c2w, np.tile([[20.0, 20, 8, 16]], (n, 1)))


def test_select_views():
    """Targets are every 8th frame; k-means inputs avoid them; given inputs are checked."""
    scene = _line_scene(20)
    ins, tgs = select_views(scene, 4)
    np.testing.assert_array_equal(tgs, [0, 8, 16])
    assert len(ins) == 4 and not set(ins) & set(tgs)
    ins, tgs = select_views(scene, 4, [8, 3])
    np.testing.assert_array_equal(ins, [3, 8])
    np.testing.assert_array_equal(tgs, [0, 16])
    with pytest.raises(ValueError, match="index 20 is out of range"):
        select_views(scene, 4, [1, 20])
    with pytest.raises(ValueError, match=r"^--num-inputs must be >= 1, got 0$"):
        select_views(scene, 0)


def test_view_size_keeps_portrait():
    scene = _line_scene(2)  # 32 high, 16 wide
    assert view_size(scene, 0, (64, None), 16)[3] == (64, 32)
    assert view_size(scene, 0, (64, 48), 16)[3] == (64, 48)
    assert view_size(scene, 0, (64, None), 16, square_crop=True)[3] == (32, 32)
    with pytest.raises(ValueError, match="width 40 is not a positive multiple of the model's patch multiple 16"):
        view_size(scene, 0, (64, 40), 16)


def _random_poses(rng, n):
    c2w = np.tile(np.eye(4), (n, 1, 1))
    c2w[:, :3, :3] = Rotation.from_rotvec(rng.normal(0, 0.3, (n, 3))).as_matrix()
    c2w[:, :3, 3] = rng.normal(0, 1, (n, 3))
    return c2w


def test_spline_path_passes_through_the_inputs(rng):
    """With (V-1)*k+1 frames the path hits every input pose (to 1e-9) and stays rigid."""
    c2w = _random_poses(rng, 5)
    path = spline_path(c2w, 4 * 6 + 1)
    np.testing.assert_allclose(path[::6], c2w, atol=1e-9)
    validate_cameras(path, np.tile([[1.0, 1, 0, 0]], (len(path), 1)))


def test_orbit_looks_at_the_common_point(rng):
    """Inputs looking at a known point: every orbit camera looks at it from one distance."""
    centre = rng.normal(0, 1, 3)
    eye = centre + rng.normal(0, 1, (6, 3)) * [3, 0.3, 3]
    fwd = centre - eye
    fwd /= np.linalg.norm(fwd, axis=1, keepdims=True)
    up = np.array([0.0, -1.0, 0.0])  # OpenCV y down: world up is -y
    right = np.cross(fwd, up)
    right /= np.linalg.norm(right, axis=1, keepdims=True)
    down = np.cross(fwd, right)
    c2w = np.tile(np.eye(4), (6, 1, 1))
    c2w[:, :3, 0], c2w[:, :3, 1], c2w[:, :3, 2], c2w[:, :3, 3] = right, down, fwd, eye
    path = orbit_path(c2w, 12)
    validate_cameras(path, np.tile([[1.0, 1, 0, 0]], (12, 1)))
    to_centre = centre - path[:, :3, 3]
    dist = np.linalg.norm(to_centre, axis=1)
    np.testing.assert_allclose(np.einsum("ni,ni->n", path[:, :3, 2], to_centre / dist[:, None]), 1.0, atol=1e-9)
    np.testing.assert_allclose(dist, dist[0], rtol=1e-9)


def test_gs_round_trip_is_exact(tmp_path, rng):
    n, m = 50, 7
    f32 = lambda *s: rng.normal(size=s).astype(np.float32)  # noqa: E731
    saved = SavedScene(
        gaussians=Gaussians(f32(n, 3), f32(n, 4), f32(n, 3), f32(n), f32(n, 48)),
        model=C.long_lrm(),
        c2w=_random_poses(rng, m),
        intrinsics=rng.uniform(10, 20, (m, 4)),
        world_from_scene=_random_poses(rng, 1)[0],
        frame_names=tuple(f"images/{i}.jpg" for i in range(m)),
        inputs=np.array([1, 3]),
        targets=np.array([0]),
        image_hw=(64, 32),
        resized_hw=(64, 36),
        crop_box=(0, 2, 64, 32),
        scene_path="/x",
        scene_format="colmap",
    )
    save_gs(str(tmp_path / "a.gs"), saved)
    back = load_gs(str(tmp_path / "a.gs"))
    for name in Gaussians._fields:
        np.testing.assert_array_equal(getattr(back.gaussians, name), getattr(saved.gaussians, name))
    for name in ("c2w", "intrinsics", "world_from_scene", "inputs", "targets"):
        np.testing.assert_array_equal(getattr(back, name), getattr(saved, name))
    assert back.model == saved.model and back.frame_names == saved.frame_names
    assert (back.image_hw, back.resized_hw, back.crop_box) == (saved.image_hw, saved.resized_hw, saved.crop_box)


def test_params_folder_round_trip_and_fit_check(tmp_path, key):
    """save_params -> load_params gives the same arrays and config; another config is
    refused naming the first mismatching parameter path and both shapes."""
    cfg = C.tiny()
    params = jax.tree.map(np.asarray, init_params(key, cfg, 1, 16, 16))
    count = save_params(str(tmp_path / "p"), params, cfg)
    assert count == sum(x.size for x in jax.tree.leaves(params))
    back, cfg_back = load_params(str(tmp_path / "p"))
    assert cfg_back == cfg
    jax.tree.map(np.testing.assert_array_equal, back, params)
    other = replace(cfg, head=replace(cfg.head, feature_dim=8))
    with pytest.raises(ValueError, match=r"first mismatch 'decoder/.*': model \(.*\), checkpoint \(.*\)"):
        load_params(str(tmp_path / "p"), other)
    with pytest.raises(ValueError, match="first mismatch"):
        check_params_fit(params, other, "x")


def test_render_views_sizes_the_splat_buffer_so_nothing_is_dropped(rng):
    """The wide Gaussians of ``tests.helpers.wide_gaussians`` overflow the trace-time buffer
    of 8 slots per Gaussian, which drops the farthest entries (the far wall of a real capture
    went missing that way). ``render_views`` sizes the buffer for its cameras: its renders
    equal ``splat.rasterize`` in "RGB" mode with room for every Gaussian in every block (atol 1e-5)."""
    from llrmpp_jax.capture.render import render_views
    from llrmpp_jax.model import render
    from llrmpp_jax.splat import SplatConfig, rasterize
    from tests.helpers.wide_gaussians import INTRINSICS, SIZE, wide_colour_scene

    g, cfg, c2w = wide_colour_scene(rng)
    n, h, w = g.means.shape[0], SIZE, SIZE
    intr = np.tile(INTRINSICS, (2, 1))
    saved = SavedScene(
        gaussians=g,
        model=cfg,
        c2w=c2w,
        intrinsics=intr,
        world_from_scene=np.eye(4),
        frame_names=("a", "b"),
        inputs=np.array([0]),
        targets=np.array([1]),
        image_hw=(h, w),
        resized_hw=(h, w),
        crop_box=(0, 0, h, w),
        scene_path="/x",
        scene_format="colmap",
    )
    default = render(
        {}, cfg, jax.tree.map(lambda x: x[None], g), c2w[None].astype(np.float32), intr[None].astype(np.float32), h, w
    )
    assert int(default.dropped.max()) > 0  # the scene overflows the trace-time buffer
    got = render_views({}, saved, c2w, intr, ["a", "b"], progress=False).rgb
    room = SplatConfig(max_intersections=n * (h // 8) * (w // 8))
    for v in range(2):
        want = rasterize(
            g.means,
            g.quats,
            g.scales,
            g.opacities,
            g.features[:, None, :],
            c2w[v].astype(np.float32),
            intr[v].astype(np.float32),
            h,
            w,
            room,
            render_mode="RGB",
            background=np.ones(3, np.float32),
        )
        assert not bool(want.stats.overflow)
        np.testing.assert_allclose(got[v], np.clip(np.asarray(want.features), 0.0, 1.0), atol=1e-5)

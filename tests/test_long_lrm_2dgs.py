"""Long-LRM 2DGS (``GaussianHeadConfig.primitive="2dgs"``, paper Table 7's Long-LRM 2DGS row).

* Head: decoded Gaussians against a per-Gaussian NumPy computation from the raw channels
  ``[xyz 3 | SH | log-scale 2 | quaternion 4 | opacity 1]`` (float64, 1e-10).
* Render: the model's RGB and depth against the brute-force float64 2DGS reference
  (``splat.reference_2dgs``; SH degree 0, whose colour is ``max(C0 c + 0.5, 0)``, the
  white background composited by hand, expected depth = accumulated z / alpha), and against
  ``splat.rasterize(..., primitive="2dgs")`` called directly.
* Bad configs: one line naming the setting.
* Training: a tiny 2DGS model overfits one procedural scene (loss after 12 Adam steps below
  80% of the first), and its depth render is finite and positive where drawn.
* Files: a .gs round trip keeps the two scales and the config, ``render_views(depth=True)``
  equals the 2DGS splatter's expected depth, a 3-scale array under a 2DGS config is refused,
  and the PLY writes the two log-scales plus ``scale_2 = log(SURFEL_THICKNESS * min)``.
"""

from dataclasses import replace

import jax
import jax.numpy as jnp
import numpy as np
import plyfile
import pytest

from llrmpp_jax import config as C
from llrmpp_jax.capture.render import render_views
from llrmpp_jax.capture.scene_file import SavedScene, load_gs, save_gs
from llrmpp_jax.data.synthetic import ProceduralConfig, procedural_scene
from llrmpp_jax.errors import UserError
from llrmpp_jax.export_ply import export_ply, read_ply
from llrmpp_jax.gaussians import SURFEL_THICKNESS, GaussianHead, Gaussians, decode_gaussians
from llrmpp_jax.model import fit_capacity, init_params, reconstruct, render
from llrmpp_jax.objective import LossWeights, make_objective
from llrmpp_jax.splat import rasterize
from llrmpp_jax.splat.reference_2dgs import render_surfels_reference
from llrmpp_jax.train.optimizer import OptimizerConfig, make_optimizer
from tests.helpers.typechecks import unchecked

SH_C0 = 0.28209479177387814


def _model(sh_degree: int = 1, **head) -> C.ModelConfig:
    head = {"max_dist": 10.0, "scale_bias": -3.0, **head}
    return replace(
        C.tiny(),
        outputs=("rgb", "depth"),
        head=C.GaussianHeadConfig(mode="color", sh_degree=sh_degree, primitive="2dgs", **head),
    )


def _cameras(rng, b, v):
    """Random rigid c2w [b, v, 4, 4] and pinhole intrinsics [b, v, 4], float64."""
    q, _ = np.linalg.qr(rng.normal(size=(b, v, 3, 3)))
    c2w = np.zeros((b, v, 4, 4))
    c2w[..., :3, :3], c2w[..., :3, 3], c2w[..., 3, 3] = q, rng.normal(size=(b, v, 3)), 1.0
    return c2w, np.broadcast_to(np.array([30.0, 28.0, 11.0, 9.0]), (b, v, 4))


def test_head_decodes_two_log_scales(rng):
    cfg = C.GaussianHeadConfig(mode="color", sh_degree=1, max_dist=6.0, primitive="2dgs")
    b, v, h, w, s = 1, 2, 2, 3, 2
    nsh = 3 * 4
    raw = rng.normal(size=(b, v, h, w, s * s, 3 + nsh + 2 + 4 + 1)) * 1.5
    c2w, intr = _cameras(rng, b, v)
    g = decode_gaussians(raw, c2w, intr, s, cfg)
    assert g.scales.shape == (b, v * h * w * s * s, 2)
    want = {k: np.zeros((b, v, h * s, w * s, c)) for k, c in (("means", 3), ("scales", 2), ("quats", 4), ("sh", nsh))}
    opac = np.zeros((b, v, h * s, w * s))
    for i in np.ndindex(b, v, h, w, s * s):
        r = raw[i]
        row, col = i[2] * s + i[4] // s, i[3] * s + i[4] % s
        fx, fy, cx, cy = intr[i[0], i[1]]
        d = c2w[i[0], i[1], :3, :3] @ np.array([(col + 0.5 - cx) / fx, (row + 0.5 - cy) / fy, 1.0])
        dist = 6.0 / (1.0 + np.exp(-np.mean(r[:3])))
        at = (i[0], i[1], row, col)
        want["means"][at] = c2w[i[0], i[1], :3, 3] + dist * d / np.linalg.norm(d)
        want["sh"][at] = r[3 : 3 + nsh]
        want["scales"][at] = np.exp(np.minimum(r[3 + nsh : 5 + nsh] + cfg.scale_bias, cfg.scale_max))
        want["quats"][at] = r[5 + nsh : 9 + nsh] / np.linalg.norm(r[5 + nsh : 9 + nsh])
        opac[at] = 1.0 / (1.0 + np.exp(-(r[9 + nsh] + cfg.opacity_bias)))
    got = {"means": g.means, "scales": g.scales, "quats": g.quats, "sh": g.features}
    for name, x in got.items():
        np.testing.assert_allclose(
            np.asarray(x), want[name].reshape(b, -1, want[name].shape[-1]), rtol=1e-10, atol=1e-10
        )
    np.testing.assert_allclose(np.asarray(g.opacities), opac.reshape(b, -1), rtol=1e-10, atol=1e-12)


def test_head_kernel_has_one_channel_less_per_gaussian(rng):
    """2DGS drops one log-scale channel per Gaussian; the 3DGS head keeps Long-LRM's layout."""
    tokens = rng.normal(size=(1, 2 * 2 * 2, 16)).astype(np.float32)
    c2w, intr = (a.astype(np.float32) for a in _cameras(rng, 1, 2))
    shapes = {}
    for prim in ("3dgs", "2dgs"):
        head = GaussianHead(C.GaussianHeadConfig(mode="color", sh_degree=3, primitive=prim), 4)
        params = head.init(jax.random.key(0), tokens, (2, 2), c2w, intr)["params"]
        shapes[prim] = params["proj"]["kernel"].shape  # pyright: ignore[reportAttributeAccessIssue] -- a params leaf is an array
    assert shapes == {"3dgs": (16, 16 * 59), "2dgs": (16, 16 * 58)}


def _one_view(rng, size=16):
    """One scene: a camera looking down +z from the origin, a target slightly behind and
    aside it, and a random image."""
    c2w = np.eye(4, dtype=np.float32)[None, None]
    target = np.eye(4, dtype=np.float32)
    target[:3, 3] = [0.05, -0.03, -0.2]
    intr = np.array([[[size, size, size / 2, size / 2]]], np.float32)
    image = rng.uniform(size=(1, 1, size, size, 3)).astype(np.float32)
    return image, c2w, intr, target[None, None], intr


def test_model_render_matches_brute_force_and_direct_splat(rng, key):
    # opaque surfels a few pixels wide: overlaps matter, and the ray-splat intersection
    # (used where the surfel, not the screen filter, sets alpha) differs from the centre
    cfg = _model(sh_degree=0, opacity_bias=1.0, scale_bias=0.0, scale_max=0.0)
    image, c2w, intr, t_c2w, t_intr = _one_view(rng)
    params = init_params(key, cfg, 1, 16, 16)
    g = reconstruct(params, cfg, image, c2w, intr)
    fitted = fit_capacity(params, cfg, g, t_c2w, t_intr, 16, 16)
    out = render(params, fitted, g, t_c2w, t_intr, 16, 16, ("rgb", "depth"))
    rgb, depth = np.asarray(out.images["rgb"][0, 0]), np.asarray(out.images["depth"][0, 0, ..., 0])
    assert int(out.dropped[0]) == 0
    f64 = lambda x: jnp.asarray(x[0], jnp.float64)  # noqa: E731
    colours = jnp.maximum(SH_C0 * f64(g.features) + 0.5, 0.0)
    ref = render_surfels_reference(
        f64(g.means), f64(g.quats), f64(g.scales), f64(g.opacities), colours,
        jnp.asarray(t_c2w[0, 0], jnp.float64), jnp.asarray(t_intr[0, 0], jnp.float64), 16, 16, cfg.splat,
    )  # fmt: skip
    alpha = 1.0 - np.asarray(ref.transmittance)
    assert alpha.min() > 0.3  # the render is mostly drawn: the comparison is not of empty canvases
    np.testing.assert_allclose(rgb, np.asarray(ref.features) + (1.0 - alpha)[..., None], atol=2e-4)
    np.testing.assert_allclose(depth, np.asarray(ref.depth) / alpha, rtol=2e-4)
    direct = rasterize(
        g.means[0], g.quats[0], g.scales[0], g.opacities[0], g.features[0].reshape(-1, 1, 3),
        jnp.asarray(t_c2w[0, 0]), jnp.asarray(t_intr[0, 0]), 16, 16, fitted.splat,
        render_mode="RGB+ED", background=jnp.ones(3, jnp.float32), primitive="2dgs",
    )  # fmt: skip
    np.testing.assert_allclose(rgb, np.asarray(direct.features), atol=1e-6)
    np.testing.assert_allclose(depth, np.asarray(direct.depth), rtol=1e-6)
    # the intersection depth mode reaches the splatter too: a tilted surfel's depth varies across it
    inter = replace(fitted, head=replace(fitted.head, surfel_depth="intersection"))
    d2 = np.asarray(render(params, inter, g, t_c2w, t_intr, 16, 16, ("depth",)).images["depth"][0, 0, ..., 0])
    ref2 = render_surfels_reference(
        f64(g.means), f64(g.quats), f64(g.scales), f64(g.opacities), colours,
        jnp.asarray(t_c2w[0, 0], jnp.float64), jnp.asarray(t_intr[0, 0], jnp.float64), 16, 16, cfg.splat,
        depth="intersection",
    )  # fmt: skip
    np.testing.assert_allclose(d2, np.asarray(ref2.depth) / alpha, rtol=2e-4)
    assert np.abs(d2 - depth).max() > 1e-3


@pytest.mark.parametrize(
    "head, match",
    [
        (dict(mode="feature", primitive="2dgs"), r"primitive='2dgs' is Long-LRM's colour head.*mode='feature'"),
        (dict(mode="color", primitive="2dgs", sh_degree=4), r"primitive='2dgs' supports sh_degree 0..3, got 4"),
        (dict(mode="color", primitive="3dgs", surfel_depth="center"), r"surfel_depth='center' is for primitive"),
        (dict(mode="color", primitive="2dgs", surfel_depth="median"), r"surfel_depth must be .*got 'median'"),
        (dict(mode="color", primitive="4dgs"), r"primitive must be '3dgs' or '2dgs', got '4dgs'"),
    ],
)
def test_bad_2dgs_configs_name_the_setting(head, match):
    with pytest.raises(UserError, match=match), unchecked():
        C.GaussianHeadConfig(**head)


def test_three_scales_under_a_2dgs_config_are_refused(rng):
    n = 4
    f32 = lambda *s: rng.normal(size=s).astype(np.float32)  # noqa: E731
    with pytest.raises(UserError, match=r"scales have 3 axes per Gaussian but .*primitive='2dgs' has 2"):
        _saved(
            Gaussians(f32(n, 3), f32(n, 4), f32(n, 3), f32(n), f32(n, 12)), _model(), np.eye(4)[None], np.ones((1, 4))
        )


def _procedural_batch(size: int = 32) -> dict:
    scene = procedural_scene(3, ProceduralConfig(height=size, width=size, num_frames=8, path_kinds=("orbit",)))
    idx_in, idx_t = [0, 3], [1, 2]
    img = lambda ids: np.stack([scene.image(i) for i in ids])[None].astype(np.float32)  # noqa: E731
    cams = lambda ids: (scene.c2w[ids][None].astype(np.float32), scene.intrinsics[ids][None].astype(np.float32))  # noqa: E731
    (ci, ki), (ct, kt) = cams(idx_in), cams(idx_t)
    return {
        "input_images": img(idx_in),
        "input_c2w": ci,
        "input_intrinsics": ki,
        "target_images": img(idx_t),
        "target_c2w": ct,
        "target_intrinsics": kt,
        "target_depth": np.stack([scene.depth(i) for i in idx_t])[None].astype(np.float32),
    }


def test_tiny_2dgs_model_overfits_one_procedural_scene(key):
    """The objective (RGB + the paper's depth loss) trains the 2DGS head: after 12 Adam steps
    the loss is below 80% of the first; its depth render is finite and positive where drawn."""
    cfg = replace(_model(sh_degree=0), head=replace(_model(sh_degree=0).head, init_std=None))
    batch = _procedural_batch()
    params = init_params(key, cfg, 2, 32, 32)
    loss_fn = make_objective(cfg, LossWeights(depth=1.0))
    tx = make_optimizer(OptimizerConfig(lr=3e-3, warmup_steps=1, total_steps=100, weight_decay=0.0))

    @jax.jit
    def step(params, opt_state):
        (loss, aux), grads = jax.value_and_grad(loss_fn, has_aux=True)(params, batch, jax.random.key(0))
        with jax.numpy_dtype_promotion("standard"):  # optax's Python-float x int32 count
            updates, opt_state = tx.update(grads, opt_state, params)
        return jax.tree.map(jnp.add, params, updates), opt_state, loss, aux

    opt_state = tx.init(params)
    losses = []
    for _ in range(12):
        params, opt_state, loss, aux = step(params, opt_state)
        losses.append(float(loss))
    assert np.all(np.isfinite(losses)) and float(aux["depth_depth"]) > 0
    assert losses[-1] < 0.8 * losses[0], losses
    g = reconstruct(params, cfg, batch["input_images"], batch["input_c2w"], batch["input_intrinsics"])
    out = render(params, cfg, g, batch["target_c2w"], batch["target_intrinsics"], 32, 32, ("rgb", "depth"))
    depth = np.asarray(out.images["depth"])
    assert np.all(np.isfinite(depth)) and depth.max() > 0 and depth.min() >= 0


def _saved(g: Gaussians, cfg: C.ModelConfig, c2w, intr) -> SavedScene:
    wfs = np.diag([2.0, 2.0, 2.0, 1.0])  # capture units: twice the scene's
    wfs[:3, 3] = [0.5, -1.0, 0.25]
    return SavedScene(
        gaussians=g,
        model=cfg,
        c2w=c2w,
        intrinsics=intr,
        world_from_scene=wfs,
        frame_names=tuple(f"f{i}.png" for i in range(len(c2w))),
        inputs=np.array([0]),
        targets=np.array([len(c2w) - 1]),
        image_hw=(16, 16),
        resized_hw=(16, 16),
        crop_box=(0, 0, 16, 16),
        scene_path="/procedural",
        scene_format="procedural",
    )


def test_gs_file_depth_render_and_ply_of_a_2dgs_scene(tmp_path, rng, key):
    cfg = _model(sh_degree=1)
    image, c2w, intr, t_c2w, t_intr = _one_view(rng)
    params = init_params(key, cfg, 1, 16, 16)
    g = jax.tree.map(lambda x: np.asarray(x[0]), reconstruct(params, cfg, image, c2w, intr))
    cams = np.concatenate([c2w[0], t_c2w[0]]), np.concatenate([intr[0], t_intr[0]])
    save_gs(str(tmp_path / "s.gs"), _saved(Gaussians(*g), cfg, *cams))
    saved = load_gs(str(tmp_path / "s.gs"))
    assert saved.model == cfg and saved.gaussians.scales.shape == (256, 2)
    np.testing.assert_array_equal(saved.gaussians.scales, g.scales)

    views = render_views(params, saved, cams[0][1:], cams[1][1:], ["t"], depth=True, progress=False)
    assert views.depth is not None
    direct = rasterize(
        jnp.asarray(g.means), jnp.asarray(g.quats), jnp.asarray(g.scales), jnp.asarray(g.opacities), None,
        jnp.asarray(cams[0][1]), jnp.asarray(cams[1][1]), 16, 16, render_mode="ED", primitive="2dgs",
    )  # fmt: skip
    np.testing.assert_allclose(views.depth[0], np.asarray(direct.depth) * 2.0, rtol=1e-5)  # capture units
    assert views.depth.min() > 0

    export_ply(str(tmp_path / "s.ply"), saved.gaussians, cfg, saved.world_from_scene)
    v = plyfile.PlyData.read(str(tmp_path / "s.ply"))["vertex"].data
    s = np.asarray(g.scales, np.float64) * 2.0
    got = np.stack([v[f"scale_{i}"] for i in range(3)], axis=-1)
    np.testing.assert_allclose(got[:, :2], np.log(s), rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(got[:, 2], np.log(SURFEL_THICKNESS * s.min(axis=1)), rtol=1e-6, atol=1e-5)
    np.testing.assert_allclose(np.stack([v["x"], v["y"], v["z"]], -1), g.means * 2.0 + [0.5, -1.0, 0.25], atol=1e-5)
    assert read_ply(str(tmp_path / "s.ply")).gaussians.scales.shape == (256, 3)  # read back as flat 3D Gaussians

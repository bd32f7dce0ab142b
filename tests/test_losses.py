"""Losses against plain torch / kornia re-implementations (float64 oracles)."""

import jax
import jax.numpy as jnp
import kornia
import numpy as np
import pytest
import torch
import torch.nn.functional as F

from llrmpp_jax.convert.vgg import convert_vgg
from llrmpp_jax.losses import depth_loss, depth_to_normals, rgb_loss, sobel
from tests.helpers.typechecks import unchecked
from tests.oracles.torch_vgg import random_torchvision_state_dict, torch_vgg_taps

# ---------------------------------------------------------------- perceptual / RGB


def torch_perceptual(sd, pred, target):
    """Long-LRM's PerceptualLoss written plainly: avg-pool VGG19, slices ending at modules 4, 9, 14, 23, 32."""
    mean = torch.tensor([0.485, 0.456, 0.406], dtype=torch.float64).view(1, 3, 1, 1)
    xp, xt = (pred - mean) * 255, (target - mean) * 255
    loss = (xp - xt).abs().mean()
    taps = [3, 8, 13, 22, 31]  # last module of each slice = relu1_2, relu2_2, relu3_2, relu4_2, relu5_2
    weights = [1 / 2.6, 1 / 4.8, 1 / 3.7, 1 / 5.6, 10 / 1.5]
    fp = torch_vgg_taps(sd, xp, "vgg19", taps, "avg")
    ft = torch_vgg_taps(sd, xt, "vgg19", taps, "avg")
    for w, a, b in zip(weights, fp, ft, strict=True):
        loss = loss + w * (a - b).abs().mean()
    return loss / 255


@pytest.fixture
def vgg19(rng):
    sd = random_torchvision_state_dict(rng, "vgg19")
    return sd, jax.tree.map(jnp.asarray, convert_vgg(sd, "vgg19"))


def _image_pair(rng, shape):
    target = rng.random(shape)
    pred = target + 0.15 * rng.standard_normal(shape)  # unclamped, as the renderer gives
    return pred, target


def test_rgb_loss_value_and_grad_match_torch(rng, vgg19):
    """MSE + 0.5 * perceptual and its gradient vs torch autograd (one VGG compile for both)."""
    sd, params = vgg19
    pred, target = _image_pair(rng, (1, 2, 32, 48, 3))  # extra leading axis
    p32, t32 = pred.astype(np.float32), target.astype(np.float32)
    (loss, aux), grad = jax.jit(jax.value_and_grad(rgb_loss, has_aux=True))(p32, t32, params)

    def nchw(x):
        return torch.tensor(x.reshape(2, 32, 48, 3), dtype=torch.float64).permute(0, 3, 1, 2)

    tp = nchw(p32).requires_grad_()
    tt = nchw(t32)
    mse = ((tp - tt) ** 2).mean()
    perc = torch_perceptual(sd, tp, tt)
    want = mse + 0.5 * perc
    want.backward()
    np.testing.assert_allclose(float(aux["mse"]), mse.item(), rtol=1e-5)
    np.testing.assert_allclose(float(aux["psnr"]), -10 * np.log10(mse.item()), rtol=1e-5)
    np.testing.assert_allclose(float(aux["perceptual"]), perc.item(), rtol=1e-4)
    np.testing.assert_allclose(float(loss), want.item(), rtol=1e-4)
    want_grad = tp.grad.permute(0, 2, 3, 1).numpy().reshape(grad.shape)  # pyright: ignore[reportOptionalMemberAccess] -- torch fills .grad in the backward() above
    rel = np.linalg.norm(np.asarray(grad) - want_grad) / np.linalg.norm(want_grad)
    assert rel <= 1e-3, rel
    # lambda = 0: plain MSE, no VGG needed.
    loss0, aux0 = rgb_loss(p32, t32, None, perceptual_weight=0.0)
    np.testing.assert_allclose(float(loss0), mse.item(), rtol=1e-5)
    assert float(aux0["perceptual"]) == 0.0


def test_rgb_loss_errors(rng):
    x = rng.random((2, 32, 48, 3)).astype(np.float32)
    with pytest.raises(ValueError, match="needs vgg_params"):
        rgb_loss(x, x, None)
    with pytest.raises(ValueError, match=r"\(2, 32, 48, 4\)"), unchecked():
        rgb_loss(x, np.zeros((2, 32, 48, 4), np.float32), None, perceptual_weight=0.0)


def test_stage_perceptual_weight_overrides_the_experiments(rng, vgg19):
    """A stage's ``perceptual_weight`` sets the training loss's perceptual term (the torch
    oracle above) on the rendered targets; None keeps the experiment's (here 0: plain MSE)."""
    from llrmpp_jax import config as C
    from llrmpp_jax.experiment import ExperimentConfig, StageConfig
    from llrmpp_jax.model import init_params, reconstruct, render
    from llrmpp_jax.objective import load_perceptual, make_loss_fn
    from tests.helpers.scenes import orbit_scene

    sd, params = vgg19
    cfg = C.tiny()
    images, c2w, intr = orbit_scene(jax.random.key(int(rng.integers(1 << 30))), 1, 3, 16, 16)
    model = init_params(jax.random.key(1), cfg, 2, 16, 16)
    batch = {
        "input_images": images[:, :2],
        "input_c2w": c2w[:, :2],
        "input_intrinsics": intr[:, :2],
        "target_images": images[:, 2:],
        "target_c2w": c2w[:, 2:],
        "target_intrinsics": intr[:, 2:],
    }

    def rendered(m):
        g = reconstruct(m, cfg, images[:, :2], c2w[:, :2], intr[:, :2])
        return render(m, cfg, g, c2w[:, 2:], intr[:, 2:], 16, 16).images["rgb"]

    pred = np.asarray(jax.jit(rendered)(model), np.float64)
    tp = torch.tensor(pred.reshape(1, 16, 16, 3)).permute(0, 3, 1, 2)
    tt = torch.tensor(np.asarray(images[:, 2:], np.float64).reshape(1, 16, 16, 3)).permute(0, 3, 1, 2)
    mse, perc = ((tp - tt) ** 2).mean().item(), torch_perceptual(sd, tp, tt).item()

    plain, sharpen = StageConfig("plain", 1, 1, 2, 1, 16), StageConfig("sharpen", 1, 1, 2, 1, 16, perceptual_weight=0.7)
    exp = ExperimentConfig("t", cfg, (plain, sharpen), perceptual_weight=0.0)
    assert [exp.perceptual_weight_of(s) for s in exp.stages] == [0.0, 0.7]
    key = jax.random.key(0)
    loss_plain, _ = jax.jit(make_loss_fn(exp, params, plain))(model, batch, key)
    loss_sharpen, aux = jax.jit(make_loss_fn(exp, params, sharpen))(model, batch, key)
    np.testing.assert_allclose(float(loss_plain), mse, rtol=1e-4)
    np.testing.assert_allclose(float(aux["perceptual"]), perc, rtol=1e-4)
    np.testing.assert_allclose(float(loss_sharpen), mse + 0.7 * perc, rtol=1e-4)
    # VGG weights are loaded when any stage needs them, and not when none does.
    assert load_perceptual(exp) is not None
    assert load_perceptual(ExperimentConfig("t", cfg, (plain,), perceptual_weight=0.0)) is None
    with pytest.raises(ValueError, match=r"stage 'x': perceptual_weight must be >= 0, got -0.5"):
        StageConfig("x", 1, 1, 2, 1, 16, perceptual_weight=-0.5)


# ---------------------------------------------------------------- Sobel / normals


@pytest.mark.parametrize("shape", [(2, 3, 9, 14), (1, 1, 16, 16), (3, 1, 2, 5)])
def test_sobel_matches_kornia(rng, shape):
    x = rng.standard_normal(shape)
    got = np.asarray(sobel(x.astype(np.float32)))
    want = kornia.filters.spatial_gradient(torch.tensor(x), mode="sobel", order=1, normalized=True).numpy()
    assert got.shape == want.shape
    np.testing.assert_allclose(got, want, atol=1e-5)
    # kornia.filters.sobel is the gradient magnitude of the same two channels.
    mag = np.sqrt(got[..., 0, :, :] ** 2 + got[..., 1, :, :] ** 2 + 1e-6)
    np.testing.assert_allclose(mag, kornia.filters.sobel(torch.tensor(x), eps=1e-6).numpy(), atol=1e-5)


def _kornia_K(intrinsics):
    """(fx, fy, cx, cy) with our +0.5 pixel centres -> kornia's 3x3 K (integer pixel centres)."""
    k = torch.zeros(intrinsics.shape[0], 3, 3, dtype=torch.float64)
    k[:, 0, 0], k[:, 1, 1] = intrinsics[:, 0], intrinsics[:, 1]
    k[:, 0, 2], k[:, 1, 2] = intrinsics[:, 2] - 0.5, intrinsics[:, 3] - 0.5
    k[:, 2, 2] = 1
    return k


def _random_depth(rng, b, h, w):
    yy, xx = np.meshgrid(np.linspace(0, 1, h), np.linspace(0, 1, w), indexing="ij")
    slope = rng.uniform(-1, 1, (b, 2, 1, 1))
    return 2.0 + slope[:, 0] * xx + slope[:, 1] * yy + 0.05 * rng.standard_normal((b, h, w))


def _random_intrinsics(rng, b, h, w):
    f = rng.uniform(0.8, 1.2, (b, 2)) * w
    c = rng.uniform(0.4, 0.6, (b, 2)) * np.array([w, h])
    return np.concatenate([f, c], axis=1)


@pytest.mark.parametrize("hw", [(12, 17), (24, 24)])
def test_depth_to_normals_matches_kornia(rng, hw):
    h, w = hw
    depth, k = _random_depth(rng, 3, h, w), _random_intrinsics(rng, 3, h, w)
    got = np.asarray(depth_to_normals(depth.astype(np.float32), k.astype(np.float32)))
    want = kornia.geometry.depth.depth_to_normals(torch.tensor(depth)[:, None], _kornia_K(torch.tensor(k)))
    np.testing.assert_allclose(got, want.permute(0, 2, 3, 1).numpy(), atol=1e-5)
    with pytest.raises(ValueError, match=r"intrinsics has shape \(3, 3\)"), unchecked():
        depth_to_normals(depth, k[:, :3])


# ---------------------------------------------------------------- depth loss


def torch_depth_loss(pred, target, intrinsics):
    """Plain torch/kornia reference of depth_loss; pred/target (B, H, W), intrinsics (B, 4)."""
    valid = torch.isfinite(target) & (target > 0)
    t = torch.where(valid, target, torch.ones_like(target))
    depth = F.smooth_l1_loss(torch.log(pred.clamp(min=1e-6))[valid], torch.log(t)[valid], beta=1.0)

    def down(s):
        v = valid.double()[:, None]
        frac = F.avg_pool2d(v, s)
        ps = F.avg_pool2d(torch.where(valid, pred, 0.0)[:, None], s) / frac.clamp(min=1 / s**2)
        ts = F.avg_pool2d(torch.where(valid, t, 0.0)[:, None], s) / frac.clamp(min=1 / s**2)
        vs = (frac > 0).double()
        eroded = -F.max_pool2d(-F.pad(vs, (1, 1, 1, 1), mode="replicate"), 3, stride=1) > 0.5
        return ps, ts, eroded

    grad = 0.0
    for s in (4, 8, 16, 32):
        ps, ts, m = down(s)
        err = (kornia.filters.spatial_gradient(ps) - kornia.filters.spatial_gradient(ts)).abs()  # (B, 1, 2, h, w)
        grad = grad + err[m[:, :, None].expand_as(err)].mean()  # one mean over dx and dy entries
    p4, t4, m4 = down(4)
    k4 = _kornia_K(intrinsics / 4)
    cos = (kornia.geometry.depth.depth_to_normals(p4, k4) * kornia.geometry.depth.depth_to_normals(t4, k4)).sum(1)
    normal = (1 - cos)[m4[:, 0]].mean()
    return depth + 0.1 * grad + 0.1 * normal, dict(depth=depth, grad=grad, normal=normal)


def test_depth_loss_matches_torch_reference(rng):
    h, w = 70, 101  # not multiples of 32: the trailing rows/columns are dropped per scale
    target = _random_depth(rng, 2, h, w)
    pred = target * np.exp(0.3 * rng.standard_normal(target.shape))
    pred[0, :5, :7] *= 8.0  # large log errors: the linear branch of smooth-L1
    holes = rng.random(target.shape) < 0.05
    target[holes] = 0.0
    target[0, 10:20, 30:50] = np.nan  # a whole block invalid at 1/4 resolution
    target[1, 3, 4], target[1, 5, 6] = np.inf, -1.0
    intrinsics = _random_intrinsics(rng, 2, h, w)
    p32, t32, k32 = pred.astype(np.float32), target.astype(np.float32), intrinsics.astype(np.float32)

    fn = jax.jit(jax.value_and_grad(depth_loss, has_aux=True))
    (loss, aux), grad = fn(p32, t32, k32)
    tp = torch.tensor(p32, dtype=torch.float64, requires_grad=True)
    want, want_aux = torch_depth_loss(
        tp, torch.tensor(t32, dtype=torch.float64), torch.tensor(k32, dtype=torch.float64)
    )
    want.backward()

    for name in ("depth", "grad", "normal"):
        np.testing.assert_allclose(float(aux[name]), want_aux[name].item(), rtol=1e-4, err_msg=name)
    np.testing.assert_allclose(float(loss), want.item(), rtol=1e-4)
    n_invalid = int(np.sum(~(np.isfinite(target) & (target > 0))))
    assert float(aux["num_invalid"]) == n_invalid
    g, wg = np.asarray(grad), tp.grad.numpy()  # pyright: ignore[reportOptionalMemberAccess] -- torch fills .grad in the backward() above
    assert np.all(np.isfinite(g))
    assert np.linalg.norm(g - wg) <= 1e-3 * np.linalg.norm(wg)


def _numpy_spatial_gradient(x):
    """kornia.filters.spatial_gradient(x) (mode "sobel", order 1, normalized) of x (B, H, W),
    written as a 3x3 cross-correlation over a replicated border: (B, 2, H, W)."""
    kx = np.array([[-1.0, 0.0, 1.0], [-2.0, 0.0, 2.0], [-1.0, 0.0, 1.0]]) / 8.0
    h, w = x.shape[-2:]
    xp = np.pad(x, ((0, 0), (1, 1), (1, 1)), mode="edge")
    out = np.zeros(x.shape[:1] + (2,) + x.shape[1:])
    for i in range(3):
        for j in range(3):
            window = xp[:, i : i + h, j : j + w]
            out[:, 0] += kx[i, j] * window
            out[:, 1] += kx[j, i] * window
    return out


def simplerecon_ms_gradient_loss(depth_gt, depth_pred, scales=(4, 8, 16, 32)):
    """SimpleRecon's MSGradientLoss.forward (nianticlabs/simplerecon losses.py) in NumPy, on
    the paper's pyramid (area means of s x s blocks) instead of its blur_pool2d one: per
    scale, the mean of |grad_pred - grad_gt| over the entries (component, pixel) whose target
    gradient is finite, summed over the scales."""
    loss = 0.0
    for s in scales:
        b, h, w = depth_gt.shape[0], depth_gt.shape[1] // s, depth_gt.shape[2] // s
        gt = depth_gt[:, : h * s, : w * s].reshape(b, h, s, w, s).mean(axis=(2, 4))
        pred = depth_pred[:, : h * s, : w * s].reshape(b, h, s, w, s).mean(axis=(2, 4))
        grad_gt = _numpy_spatial_gradient(gt)
        mask = np.isfinite(grad_gt)
        loss += np.mean(np.abs(_numpy_spatial_gradient(pred)[mask] - grad_gt[mask]))
    return loss


def test_gradient_term_is_simplerecon_s_ms_gradient_loss(rng):
    """The ``grad`` term against a NumPy transcription of SimpleRecon's MSGradientLoss on
    fresh random depths in (0.5, 5) m (no invalid pixels), float64 oracle, rtol 1e-5: the
    mean over dx and dy entries, half of the old sum mean|dx| + mean|dy|."""
    h, w = 96, 136
    target = rng.uniform(0.5, 5.0, (3, h, w))
    pred = rng.uniform(0.5, 5.0, (3, h, w))
    intrinsics = _random_intrinsics(rng, 3, h, w)
    _, aux = jax.jit(depth_loss)(pred.astype(np.float32), target.astype(np.float32), intrinsics.astype(np.float32))
    want = simplerecon_ms_gradient_loss(
        target.astype(np.float32).astype(np.float64), pred.astype(np.float32).astype(np.float64)
    )
    np.testing.assert_allclose(float(aux["grad"]), want, rtol=1e-5)


def test_depth_loss_errors(rng):
    d = rng.uniform(1, 2, (2, 32, 40)).astype(np.float32)
    k = np.ones((2, 4), np.float32)
    with pytest.raises(ValueError, match="need H, W >= 32"):
        depth_loss(d[:, :16], d[:, :16], k)
    with pytest.raises(ValueError, match=r"intrinsics has shape \(4,\)"), unchecked():
        depth_loss(d, d, k[0])
    with pytest.raises(ValueError, match=r"pred_depth \(2, 32, 39\)"), unchecked():
        depth_loss(d[..., :39], d, k)

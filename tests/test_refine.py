"""Post-prediction refinement: it recovers known Gaussians and lowers the feature-mode loss."""

from dataclasses import replace

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from llrmpp_jax import config as C
from llrmpp_jax.data.camera_paths import look_at
from llrmpp_jax.gaussians import Gaussians
from llrmpp_jax.metrics import psnr
from llrmpp_jax.model import init_params, reconstruct, render
from llrmpp_jax.refine import (
    RefineConfig,
    from_unconstrained,
    heldout_psnr,
    rate_scale_for,
    refine,
    to_unconstrained,
)

H = W = 32
COLOUR = C.ModelConfig(head=C.GaussianHeadConfig(mode="color", sh_degree=1))


def known_scene(rng, n=300, views=12):
    """Random SH-degree-1 Gaussians in a 1.2-unit cube, cameras on an arc 2.5 units out."""
    q = rng.normal(size=(n, 4))
    sh = np.concatenate([rng.uniform(-1.5, 1.5, (n, 1, 3)), rng.normal(0, 0.2, (n, 3, 3))], axis=1)
    g = Gaussians(
        rng.uniform(-0.6, 0.6, (n, 3)),
        q / np.linalg.norm(q, axis=-1, keepdims=True),
        np.exp(rng.uniform(-3.2, -2.2, (n, 3))),
        rng.uniform(0.5, 0.95, n),
        sh.reshape(n, 12),  # pyright: ignore[reportArgumentType] -- a NumPy array where jax.Array is annotated: both work
    )
    ang = np.linspace(-0.9, 0.9, views)
    eye = np.stack([2.5 * np.sin(ang), -2.5 * np.cos(ang), 0.6 + 0.2 * np.cos(3 * ang)], -1)
    c2w = look_at(eye, np.zeros_like(eye))
    intr = np.tile([[32.0, 32.0, 16.0, 16.0]], (views, 1))
    f32 = lambda a: jnp.asarray(a, jnp.float32)[None]  # noqa: E731
    return Gaussians(*(f32(a) for a in g)), f32(c2w), f32(intr)


def perturb(rng, g: Gaussians) -> Gaussians:
    y = to_unconstrained(g, COLOUR)
    sd = {"means": 0.05, "log_scales": 0.4, "quats": 0.2, "opacity_logits": 1.0, "sh_dc": 0.5, "sh_rest": 0.5}
    return from_unconstrained({k: v + jnp.asarray(rng.normal(0, sd[k], v.shape), jnp.float32) for k, v in y.items()})


def test_unconstrained_round_trip(rng):
    g, _, _ = known_scene(rng, n=50)
    back = from_unconstrained(to_unconstrained(g, COLOUR))
    for name, a, b in zip(Gaussians._fields, back, g, strict=True):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-6, atol=1e-7, err_msg=name)


@pytest.mark.slow
def test_refine_recovers_perturbed_known_gaussians(rng):
    """Ground truth = the splatter's render of known Gaussians; 8 input views, 4 held out.

    From perturbed Gaussians (~20 dB held out), 30 steps must gain >= 5 dB on the held-out
    views (about 13 dB in practice) and lower the input-view loss.
    """
    true, c2w, intr = known_scene(rng)
    images = render({}, COLOUR, true, c2w, intr, H, W).images["rgb"]
    held = np.arange(12) % 3 == 1
    inp, tgt = np.where(~held)[0], np.where(held)[0]
    start = perturb(rng, true)
    rc = RefineConfig(
        lr_means=1e-2,
        lr_log_scales=2e-2,
        lr_quats=1e-2,
        lr_opacity_logits=5e-2,
        lr_features=3e-2,
        sh_rest_lr_factor=1.0,
    )
    refined, info = refine({}, COLOUR, start, images[:, inp], c2w[:, inp], intr[:, inp], steps=30, rc=rc)
    before = heldout_psnr({}, COLOUR, start, images[:, tgt], c2w[:, tgt], intr[:, tgt])
    after = heldout_psnr({}, COLOUR, refined, images[:, tgt], c2w[:, tgt], intr[:, tgt])
    assert after - before >= 5.0, (before, after)
    assert info.steps == 30 and info.losses.shape == (31,) and info.dropped == 0
    assert info.losses[-1] < 0.2 * info.losses[0]
    # The recorded losses are the MSE of the renders they claim (first and last).
    for g, loss in ((start, info.losses[0]), (refined, info.losses[-1])):
        rgb = render({}, COLOUR, g, c2w[:, inp], intr[:, inp], H, W).images["rgb"]
        np.testing.assert_allclose(float(jnp.mean(jnp.square(rgb - images[:, inp]))), loss, rtol=1e-4)
    # heldout_psnr is the mean of metrics.psnr over the held-out views.
    rgb = render({}, COLOUR, refined, c2w[:, tgt], intr[:, tgt], H, W).images["rgb"]
    np.testing.assert_allclose(after, float(jnp.mean(psnr(rgb, images[:, tgt]))), rtol=1e-6)


@pytest.mark.slow
def test_refine_lowers_feature_mode_loss_with_frozen_decoder(key):
    """Tiny feature model, random init: 5 steps strictly lower the input-view loss, the
    decoder is untouched (params are an input only), every optimised field moves."""
    cfg = replace(
        C.tiny(), head=C.GaussianHeadConfig(gaussians_per_token=4, feature_dim=16, max_dist=4.0, scale_bias=-3.0)
    )
    k0, k1 = jax.random.split(key)
    images = jax.random.uniform(k1, (1, 2, H, W, 3), jnp.float32)
    eye = np.array([[0.3, 0.0, -2.0], [-0.3, 0.1, -2.0]])
    c2w = jnp.asarray(look_at(eye, np.zeros_like(eye)), jnp.float32)[None]
    intr = jnp.asarray(np.tile([[32.0, 32.0, 16.0, 16.0]], (1, 2, 1)), jnp.float32)
    params = init_params(k0, cfg, 2, H, W)
    g = reconstruct(params, cfg, images, c2w, intr)
    refined, info = refine(params, cfg, g, images, c2w, intr, steps=5)
    assert info.steps == 5
    assert np.all(np.diff(info.losses) < 0), info.losses
    for name, a, b in zip(Gaussians._fields, refined, g, strict=True):
        assert a.shape == b.shape and a.dtype == b.dtype, name
        assert float(jnp.max(jnp.abs(a - b))) > 0, name


@pytest.mark.parametrize("views", [3, 5])
def test_a_step_fits_the_views_its_key_draws(rng, views):
    """With ``views_per_step=1`` an update on V views is the update on the one view that
    ``permutation(fold_in(key, 0), V)[0]`` picks, fitted alone; the recorded first and last
    losses are that view's before and after."""
    g, c2w, intr = known_scene(rng, n=60, views=views)
    images = jnp.asarray(rng.uniform(0.1, 0.9, (1, views, H, W, 3)), jnp.float32)
    key = jax.random.key(int(rng.integers(1 << 30)))
    rc = RefineConfig(views_per_step=1)
    got, info = refine({}, COLOUR, g, images, c2w, intr, steps=1, rc=rc, key=key)
    j = int(jax.random.permutation(jax.random.fold_in(key, 0), views)[0])
    want, _ = refine(
        {},
        COLOUR,
        g,
        images[:, j : j + 1],
        c2w[:, j : j + 1],
        intr[:, j : j + 1],
        steps=1,
        rc=rc,
        key=jax.random.key(7),
    )
    for name, a, b in zip(Gaussians._fields, got, want, strict=True):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-5, atol=1e-6, err_msg=name)
    assert info.views_per_step == 1 and info.steps == 1 and info.losses.shape == (2,)
    for start, loss in ((g, info.losses[0]), (got, info.losses[-1])):
        rgb = render({}, COLOUR, start, c2w[:, j : j + 1], intr[:, j : j + 1], H, W).images["rgb"]
        np.testing.assert_allclose(float(jnp.mean(jnp.square(rgb - images[:, j : j + 1]))), loss, rtol=1e-4)


def test_refine_sizes_the_splat_buffer_from_the_scene(rng):
    """The capacity is ceil(1.25 x the most pairs any input view needs) rounded up to the
    next m 2^e (m in 8..15), the pairs counted here view by view by the binning of a render
    (``stats.num_intersections``)."""
    from llrmpp_jax.splat import rasterize

    g, c2w, intr = known_scene(rng, n=80, views=3)
    images = jnp.asarray(rng.uniform(0.1, 0.9, (1, 3, H, W, 3)), jnp.float32)
    _, info = refine({}, COLOUR, g, images, c2w, intr, steps=1)
    most = max(
        int(
            rasterize(
                g.means[0],
                g.quats[0],
                g.scales[0],
                g.opacities[0],
                None,
                c2w[0, v],
                intr[0, v],
                H,
                W,
                COLOUR.splat,
                render_mode="D",
            ).stats.num_intersections
        )
        for v in range(3)
    )
    want = int(np.ceil(1.25 * most))
    sizes = sorted({m << e for m in range(8, 16) for e in range(24)})
    assert info.capacity == min(x for x in sizes if x >= want) and info.dropped == 0
    assert info.compile_s > 0 and info.step_s > 0


def test_refine_rejects_bad_arguments(rng):
    g, c2w, intr = known_scene(rng, n=10, views=2)
    images = jnp.zeros((1, 2, H, W, 3), jnp.float32)
    with pytest.raises(ValueError, match="steps"):
        refine({}, COLOUR, g, images, c2w, intr, steps=-1)
    with pytest.raises(ValueError, match="vgg_params"):
        refine({}, COLOUR, g, images, c2w, intr, rc=RefineConfig(perceptual_weight=0.5))
    with pytest.raises(ValueError, match=r"^RefineConfig.views_per_step must be >= 1, got 0$"):
        RefineConfig(views_per_step=0)


def test_rate_scale_is_100_over_steps_clipped():
    for steps, scale in [(1, 10.0), (4, 10.0), (10, 10.0), (25, 4.0), (40, 2.5), (100, 1.0), (1000, 1.0)]:
        assert rate_scale_for(steps) == pytest.approx(scale, rel=1e-12), steps


def test_default_rates_scale_with_the_steps(rng):
    """``rate_scale=None`` multiplies every field's rate by :func:`rate_scale_for` the steps
    (10 at 4 steps): the same fit as those rates multiplied by hand with ``rate_scale=1``."""
    steps, scale = 4, 10.0
    g, c2w, intr = known_scene(rng, n=40, views=2)
    images = jnp.asarray(rng.uniform(0.1, 0.9, (1, 2, H, W, 3)), jnp.float32)
    base = RefineConfig()
    by_hand = RefineConfig(
        rate_scale=1.0,
        lr_means=base.lr_means * scale,
        lr_log_scales=base.lr_log_scales * scale,
        lr_quats=base.lr_quats * scale,
        lr_opacity_logits=base.lr_opacity_logits * scale,
        lr_features=base.lr_features * scale,
    )
    got, _ = refine({}, COLOUR, g, images, c2w, intr, steps=steps)
    want, _ = refine({}, COLOUR, g, images, c2w, intr, steps=steps, rc=by_hand)
    unscaled, _ = refine({}, COLOUR, g, images, c2w, intr, steps=steps, rc=RefineConfig(rate_scale=1.0))
    for name, a, b, c in zip(Gaussians._fields, got, want, unscaled, strict=True):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-5, atol=1e-6, err_msg=name)
        assert float(jnp.max(jnp.abs(a - c))) > 1e-4, name  # the scale is not a no-op

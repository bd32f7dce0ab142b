"""Long-LRM's Gaussian pruning and gaussian_usage on the golden fixture; its wiring into
training and evaluation; the official counts at 32 views of 960x544.

Oracles: the official code's arithmetic and ranking written out here (Python floats,
``int`` truncation, a descending sort of the opacity *logits* from the golden file), and
the golden ``gaussian_usage`` computed by the official code.
"""

from dataclasses import replace

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from llrmpp_jax import config as C
from llrmpp_jax.experiment import ExperimentConfig, StageConfig
from llrmpp_jax.gaussians import Gaussians
from llrmpp_jax.model import init_params, reconstruct, render
from llrmpp_jax.pruning import gaussian_usage, prune_gaussians
from tests.helpers.environment import shared_path
from tests.helpers.scenes import orbit_scene


def official_counts(n: int, prune_ratio: float, random_ratio: float) -> tuple[int, int]:
    """Long-LRM ``model/llrm.py``: the same lines, in the same order."""
    keep_ratio = 1 - prune_ratio
    random_ratio = keep_ratio * random_ratio
    keep_ratio = keep_ratio - random_ratio
    return int(n * keep_ratio), int(n * random_ratio)


def golden_gaussians() -> tuple[Gaussians, np.ndarray, np.ndarray]:
    """The golden model's Gaussians (float64) with each one's index appended to its features."""
    out = np.load(shared_path("golden", "long_lrm_tiny", "outputs.npz"))
    b, n = out["xyz"].shape[:2]
    logits = out["opacity"][..., 0]
    index = np.broadcast_to(np.arange(n, dtype=np.float64), (b, n))[..., None]
    g = Gaussians(
        means=jnp.asarray(out["xyz"]),
        quats=jnp.asarray(out["render_quats"]),
        scales=jnp.asarray(out["render_scales"]),
        opacities=jnp.asarray(out["render_opacities"]),
        features=jnp.asarray(np.concatenate([out["feature"].reshape(b, n, -1), index], axis=-1)),
    )
    return g, logits, out["gaussian_usage"]


def test_golden_stage3_pruning_keeps_official_count_and_top_opacity(key):
    g, logits, usage = golden_gaussians()
    b, n = logits.shape
    num_top, num_random = official_counts(n, 0.6, 0.1)
    assert (num_top, num_random) == (1105, 122)
    pruned = prune_gaussians(g, 0.6, 0.1, key)
    assert pruned.opacities.shape == (b, num_top + num_random)
    kept = np.asarray(pruned.features[..., -1]).astype(int)  # original indices
    ranks = []
    for s in range(b):
        order = np.argsort(-logits[s], kind="stable")
        assert logits[s, order[num_top - 1]] > logits[s, order[num_top]]  # no tie at the cut
        np.testing.assert_array_equal(kept[s, :num_top], order[:num_top])  # top ones, in order
        rest = kept[s, num_top:]
        assert len(set(rest.tolist())) == num_random and not set(rest.tolist()) & set(order[:num_top].tolist())
        ranks.append(np.argsort(order)[rest])
        # every field of a kept Gaussian is that Gaussian's
        for name in ("means", "quats", "scales", "opacities"):
            np.testing.assert_array_equal(
                np.asarray(getattr(pruned, name))[s], np.asarray(getattr(g, name))[s, kept[s]]
            )
    np.testing.assert_array_equal(ranks[0], ranks[1])  # one permutation of rank positions for the batch
    other = np.asarray(prune_gaussians(g, 0.6, 0.1, jax.random.fold_in(key, 1)).features[0, num_top:, -1])
    assert set(other.astype(int).tolist()) != set(kept[0, num_top:].tolist())  # the key draws the random share
    # gaussian_usage: the official value (computed in float32 upstream) before pruning
    np.testing.assert_allclose(np.asarray(gaussian_usage(g.opacities)), usage, rtol=0, atol=1e-6)
    assert prune_gaussians(g, 0.0, 0.1, key) is g


def test_released_checkpoint_config_prunes_like_the_official_code_at_960x540():
    """The released checkpoint's config at 32 inputs of 960x544 (540 rounded to 16): shapes only."""
    cfg = C.long_lrm_i540()
    params = jax.eval_shape(lambda k: init_params(k, cfg, 1, 16, 16), jax.random.key(0))
    images = jax.ShapeDtypeStruct((1, 32, 544, 960, 3), jnp.float32)
    c2w = jax.ShapeDtypeStruct((1, 32, 4, 4), jnp.float32)
    intr = jax.ShapeDtypeStruct((1, 32, 4), jnp.float32)

    def recon_and_prune(p, i, c, k):
        g = reconstruct(p, cfg, i, c, k)
        return prune_gaussians(g, cfg.head.prune_ratio, cfg.head.prune_random_ratio, jax.random.key(0))

    g = jax.eval_shape(recon_and_prune, params, images, c2w, intr)
    n = 32 * 544 * 960
    assert g.means.shape == (1, sum(official_counts(n, 0.6, 0.1)), 3) == (1, 6_016_204 + 668_467, 3)


@pytest.mark.slow  # ~30 s idle, 2 min on a busy 2-core box: compiles the evaluator and the train loss
def test_training_and_evaluation_prune_and_log_usage(key):
    """Colour model with pruning: the evaluator renders the pruned set (its key), the train
    loss renders with pruning and logs gaussian_usage."""
    from llrmpp_jax.evaluate import predict
    from llrmpp_jax.objective import make_loss_fn

    cfg = replace(
        C.tiny(),
        head=C.GaussianHeadConfig(
            mode="color", sh_degree=1, max_dist=4.0, scale_bias=-3.0, prune_ratio=0.6, prune_random_ratio=0.1
        ),
    )
    images, c2w, intr = orbit_scene(key, 1, 3, 16, 16)
    params = init_params(jax.random.key(1), cfg, 2, 16, 16)
    sample = {
        "input_images": images[:, :2],
        "input_c2w": c2w[:, :2],
        "input_intrinsics": intr[:, :2],
        "target_images": images[:, 2:],
        "target_c2w": c2w[:, 2:],
        "target_intrinsics": intr[:, 2:],
    }
    g = reconstruct(params, cfg, images[:, :2], c2w[:, :2], intr[:, :2])
    pk = jax.random.key(5)
    want = render(params, cfg, prune_gaussians(g, 0.6, 0.1, pk), c2w[:, 2:], intr[:, 2:], 16, 16).images["rgb"]
    unpruned = render(params, cfg, g, c2w[:, 2:], intr[:, 2:], 16, 16).images["rgb"]
    out = predict(params, cfg, sample, pk)
    np.testing.assert_allclose(np.asarray(out["rgb"]), np.asarray(want), rtol=0, atol=1e-6)
    assert np.abs(np.asarray(unpruned) - np.asarray(want)).max() > 1e-4
    np.testing.assert_allclose(np.asarray(out["gaussian_usage"]), np.asarray(gaussian_usage(g.opacities)))

    exp = ExperimentConfig("t", cfg, (StageConfig("s", 1, 1, 2, 1, 16),), perceptual_weight=0.0)
    loss, aux = jax.jit(make_loss_fn(exp, None))(params, sample, pk)
    mse = float(jnp.mean(jnp.square(want - images[:, 2:])))
    np.testing.assert_allclose(float(aux["mse"]), mse, rtol=1e-5)
    np.testing.assert_allclose(float(aux["gaussian_usage"]), float(gaussian_usage(g.opacities)[0]))


def test_pruning_config_errors():
    with pytest.raises(ValueError, match=r"pruning is Long-LRM's colour-mode recipe; mode='feature'"):
        C.GaussianHeadConfig(prune_ratio=0.6)
    with pytest.raises(ValueError, match=r"0 <= prune_ratio < 1 .* got 1.0 and 0.1"):
        C.GaussianHeadConfig(mode="color", prune_ratio=1.0, prune_random_ratio=0.1)

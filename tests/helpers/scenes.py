"""Small random model inputs: views of random images from cameras around the origin."""

import jax
import jax.numpy as jnp


def orbit_scene(key, b, v, h, w):
    """Random images and cameras looking at the origin from ~2 units (non-degenerate)."""
    k1, k2 = jax.random.split(key)
    images = jax.random.uniform(k1, (b, v, h, w, 3), jnp.float32)
    angles = jax.random.uniform(k2, (b, v), jnp.float32, -0.4, 0.4)
    c, s = jnp.cos(angles), jnp.sin(angles)
    zero, one = jnp.zeros_like(c), jnp.ones_like(c)
    rot = jnp.stack([jnp.stack([c, zero, -s], -1), jnp.stack([zero, one, zero], -1), jnp.stack([s, zero, c], -1)], -2)
    centre = jnp.stack([2.0 * s, zero, -2.0 * c], -1)
    c2w = (
        jnp.zeros((b, v, 4, 4), jnp.float32).at[..., :3, :3].set(rot).at[..., :3, 3].set(centre).at[..., 3, 3].set(1.0)
    )
    intr = jnp.broadcast_to(jnp.array([w, w, w / 2, h / 2], jnp.float32), (b, v, 4))
    return images, c2w, intr


def orbit_batch(key, inputs: int, targets: int, size: int, depth: bool = False) -> dict:
    """A training batch of one :func:`orbit_scene`: ``inputs`` input and ``targets`` target views
    of ``size`` x ``size``, and with ``depth`` random ground-truth depths in [0.5, 4]."""
    k_scene, k_depth = jax.random.split(key)
    images, c2w, intr = orbit_scene(k_scene, 1, inputs + targets, size, size)
    batch = {
        "input_images": images[:, :inputs],
        "input_c2w": c2w[:, :inputs],
        "input_intrinsics": intr[:, :inputs],
        "target_images": images[:, inputs:],
        "target_c2w": c2w[:, inputs:],
        "target_intrinsics": intr[:, inputs:],
    }
    if depth:
        batch["target_depth"] = jax.random.uniform(k_depth, (1, targets, size, size), jnp.float32, 0.5, 4.0)
    return batch

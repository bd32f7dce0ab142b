"""A colour-mode scene whose Gaussians each need ~30 (Gaussian, block) slots at 64x64, beyond
the splatter's trace-time buffer of 8 per Gaussian: renders that do not size their buffer
drop the farthest entries."""

from __future__ import annotations

import numpy as np

from llrmpp_jax import config as C
from llrmpp_jax.capture.bake import colour_config
from llrmpp_jax.config import ModelConfig
from llrmpp_jax.gaussians import Gaussians

SIZE = 64  # pixels, square views
INTRINSICS = np.array([50.0, 50.0, 32.0, 32.0])


def wide_colour_scene(rng: np.random.Generator, n: int = 300) -> tuple[Gaussians, ModelConfig, np.ndarray]:
    """``(Gaussians with SH degree 0, its colour config, two cameras c2w [2, 4, 4])``; the
    cameras' intrinsics are :data:`INTRINSICS` at :data:`SIZE`."""
    z = rng.uniform(1.5, 4.0, n)
    means = np.stack([rng.uniform(-0.6, 0.6, n) * z, rng.uniform(-0.6, 0.6, n) * z, z], -1)
    g = Gaussians(
        means.astype(np.float32),  # pyright: ignore[reportArgumentType] -- a NumPy array where jax.Array is annotated: both work
        rng.normal(size=(n, 4)).astype(np.float32),  # pyright: ignore[reportArgumentType] -- a NumPy array where jax.Array is annotated: both work
        rng.uniform(0.1, 0.3, (n, 3)).astype(np.float32),  # pyright: ignore[reportArgumentType] -- a NumPy array where jax.Array is annotated: both work
        rng.uniform(0.05, 0.6, n).astype(np.float32),  # pyright: ignore[reportArgumentType] -- a NumPy array where jax.Array is annotated: both work
        rng.normal(0.0, 0.5, (n, 3)).astype(np.float32),  # pyright: ignore[reportArgumentType] -- a NumPy array where jax.Array is annotated: both work
    )
    c2w = np.tile(np.eye(4), (2, 1, 1))
    c2w[1, :3, 3] = [0.2, -0.1, 0.1]
    return g, colour_config(C.tiny(), 0), c2w

"""A toy training problem for the train step, checkpoint and multi-host tests: a 2-layer MLP
regression, its batches and optimizer settings, and the plain single-device full-batch
AdamW steps (value_and_grad of the global-batch loss + optax update) it must equal."""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import optax

from llrmpp_jax.train.optimizer import OptimizerConfig

CFG = OptimizerConfig(lr=1e-2, warmup_steps=2, total_steps=20)


def toy_params(key, width: int = 16) -> dict:
    """2-layer MLP ``[B, 3] -> [B]`` parameters (float32)."""
    k1, k2 = jax.random.split(key)
    return {
        "dense1": {
            "kernel": jax.random.normal(k1, (3, width), jnp.float32),
            "bias": jnp.full((width,), 0.1, jnp.float32),
        },
        "dense2": {
            "kernel": jax.random.normal(k2, (width, 1), jnp.float32) / width,
            "bias": jnp.zeros((1,), jnp.float32),
        },
    }


def toy_loss(params, batch, key):
    """Mean squared error of the MLP on ``batch = {"image": [B, 3], "target": [B]}``."""
    del key
    dtype = params["dense1"]["kernel"].dtype
    h = jnp.tanh(batch["image"].astype(dtype) @ params["dense1"]["kernel"] + params["dense1"]["bias"][None, :])
    pred = (h @ params["dense2"]["kernel"] + params["dense2"]["bias"][None, :])[:, 0]
    err = pred.astype(jnp.float32) - batch["target"]
    return jnp.mean(jnp.square(err)), {"mae": jnp.mean(jnp.abs(err))}


def toy_batch(rng, n: int = 8) -> dict:
    return {
        "image": rng.normal(size=(n, 3)).astype(np.float32),
        "target": rng.normal(size=(n,)).astype(np.float32),
    }


@functools.partial(jax.jit, static_argnums=(0, 1))
def _oracle_update(tx, loss, params, opt_state, batch):
    (value, aux), grads = jax.value_and_grad(lambda p: loss(p, batch, None), has_aux=True)(params)
    with jax.numpy_dtype_promotion("standard"):
        updates, opt_state = tx.update(grads, opt_state, params)
    return optax.apply_updates(params, updates), opt_state, value, aux


def oracle_steps(params, tx, batches, loss=toy_loss):
    """Plain full-batch AdamW steps on one device (no collectives).

    Returns the final params and, per step, the loss and metrics before the update.
    """
    opt_state = tx.init(params)
    history = []
    for batch in batches:
        params, opt_state, value, aux = _oracle_update(tx, loss, params, opt_state, batch)
        history.append((value, aux))
    return params, history


def assert_tree_close(a, b, atol):
    for (path, x), y in zip(jax.tree_util.tree_leaves_with_path(a), jax.tree.leaves(b)):
        np.testing.assert_allclose(np.asarray(x), np.asarray(y), rtol=0, atol=atol, err_msg=jax.tree_util.keystr(path))


def assert_tree_equal(a, b):
    for (path, x), y in zip(jax.tree_util.tree_leaves_with_path(a), jax.tree.leaves(b)):
        assert np.array_equal(np.asarray(x), np.asarray(y)), jax.tree_util.keystr(path)

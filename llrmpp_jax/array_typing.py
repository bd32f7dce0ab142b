"""One legend of shape letters, used in every docstring and jaxtyping annotation.

    B  batch (scenes)                  V  input views        T  target views
    H, W  image height / width (px)    h, w  token grid (H/p, W/p)
    p  patch size                      L  sequence length (tokens)
    D  backbone width                  E  decoder width
    N  number of Gaussians             K  Gaussians per token
    F  Gaussian feature width          S  partition copies
    nh number of heads                 hd head dim
    n  SSM state size (d_state)        P  SSM head dim ("headdim")
    k  neighbours per token (local attention)
    C  channels

Arrays are ``jax.Array`` or NumPy arrays; annotations are checked only where a test
asks for it (jaxtyping's import hook), never at run time in library code.
"""

from typing import TypeAlias

import jax
import numpy as np
from jaxtyping import Array, Bool, Float, Int, PRNGKeyArray, Shaped  # noqa: F401

ArrayLike: TypeAlias = jax.Array | np.ndarray
KeyArray: TypeAlias = PRNGKeyArray

__all__ = ["Array", "ArrayLike", "Bool", "Float", "Int", "KeyArray", "Shaped"]

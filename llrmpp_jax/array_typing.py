"""One legend of axis names, used in every docstring and jaxtyping annotation.

Every name an annotation of the package uses has a line here and one meaning everywhere
(``tests/test_array_typing.py`` holds the annotations to it). Case matters: ``H`` and
``h`` are different axes. Within one call, a name is one size across all the arguments
and the return value that use it; ``#`` marks an axis that may also be 1 (broadcast).

Scenes and images
    B           batch (scenes)
    *batch      any leading batch axes, the same ones in every argument naming them
    V           input views of a scene
    T           target views of a scene
    frames      all frames of a scene, a camera path or a video
    views       frames picked by index (inputs or targets)
    candidates  frames a view selection may pick from
    H           image height (pixels)
    W           image width (pixels)
    Ho          image height after resampling (pixels)
    Wo          image width after resampling (pixels)
    C           channels
    Ci          input channels of a layer
    Co          output channels of a layer

Tokens (backbone and decoder)
    p           patch size (pixels)
    h           token grid height (H/p)
    w           token grid width (W/p)
    L           sequence length (tokens)
    Lq          query tokens
    Lk          key tokens
    Lm          tokens after a token merge
    G           global tokens
    pC          values per patch token (p*p*C)
    D           backbone width
    Din         width before a token merge
    Dout        width after a token merge
    E           decoder width
    nh          attention or SSM heads
    hd          head dim
    kn          neighbours per token (local attention)
    U           distinct neighbour offsets on the grid (local attention)

Mamba2 / SSD scan
    b           the leading batch axes flattened into one
    n           SSM state size (d_state)
    P           SSM head dim (headdim)
    g           head groups (ngroups)
    hg          heads per group (nh / g)
    hgP         one group's state columns (hg*P)
    di          inner width (expand * D)
    gn          B / C projection width (g*n)
    kw          causal convolution width (d_conv)
    Q           chunk length (tokens)
    c           chunks
    t           steps of a running sum (a chunk's tokens, or the chunks)

Gaussians and rendering
    N           Gaussians
    K           Gaussians per token
    F           Gaussian feature width
    S           partition copies
    M           target images the decoder renders at once (B*T)
    Hc          canvas height (H/r)
    Wc          canvas width (W/r)
    sh          SH coefficients stored per colour channel (at least bases)
    bases       SH basis functions up to a degree ((degree+1)^2)
    tiles       tiles of an image (binning)
    isect       slots of the (Gaussian, tile) intersection buffer
    groups      tile groups of the compositor
    group       tiles in one group
    chunk       list entries composited per step
    pix         pixels of a compositor tile
    steps       updates a refinement took

Data
    pts         points (a point cloud, keypoints, texture lookups)
    params      camera model parameters (COLMAP)
    track       observations of one 3-D point (COLMAP)
    textures    textures looked up by name
    boxes       boxes of a procedural scene
    spheres     spheres of a procedural scene
    quads       rectangles of a procedural scene

Arrays are ``jax.Array`` (``Array``) or, where a function also takes NumPy,
``ArrayLike``. Annotations are checked only in the test suite (``tests/conftest.py``
installs jaxtyping's import hook with beartype), never at run time in library code.
"""

from typing import TypeAlias

import jax
import numpy as np
from jax.typing import DTypeLike
from jaxtyping import Array, Bool, Float, Int, PRNGKeyArray, Shaped, UInt32

ArrayLike: TypeAlias = jax.Array | np.ndarray
# A size or count as callers pass it: a Python int or a NumPy one (``tuple(scene.hw[i])``).
IntLike: TypeAlias = int | np.integer
KeyArray: TypeAlias = PRNGKeyArray

__all__ = ["Array", "ArrayLike", "Bool", "DTypeLike", "Float", "Int", "IntLike", "KeyArray", "Shaped", "UInt32"]

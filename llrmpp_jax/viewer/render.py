"""One view of a reconstructed scene, for the interactive viewer (no browser involved).

* :func:`viewport_camera` -- the render size and pixel intrinsics that fill a browser
  viewport of a given vertical field of view and aspect ratio.
* :func:`render_view` -- pure: ``(params, cfg, gaussians, camera, size, output, S)`` ->
  ``[H, W, C]``. ``output="rgb"`` is the model's own render (feature mode: splat + decoder;
  colour mode: SH splat). ``output="depth"`` is the decoder's depth head where the model
  has one, otherwise the Gaussians' alpha-normalised splatted depth (camera z).
* :func:`display_image` -- ``[H, W, C]`` render -> ``uint8 [H, W, 3]`` for the screen.
* :class:`ViewRenderer` -- :func:`render_view` compiled once per (size, output, S) and
  kept, with compile and render times reported separately. Its splat buffer is sized per
  render size from the scene's input cameras (``VIEW_HEADROOM`` x the most they need, and no
  less than the trace-time default): the trace-time 8 slots per Gaussian alone can overflow
  a full-height colour render, which drops the farthest Gaussians (holes where the far wall
  should be).

Partition count: a feature-mode model trained with S partition copies can be viewed with
any ``1 <= s <= S``: the Gaussians' partition weights are the softmax over the first ``s``
logits and the decoder merges ``s`` copies (``s = 1`` is "no partitioning", opacity
unchanged; ``s = S`` is the trained model). The merge weights are a per-copy linear, so
both steps take any number of copies.
"""

from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import replace
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from llrmpp_jax.array_typing import Array, Float
from llrmpp_jax.compile_cache import CompileWatch
from llrmpp_jax.config import ModelConfig
from llrmpp_jax.errors import UserError
from llrmpp_jax.gaussian_depth import splat_depth_view
from llrmpp_jax.gaussians import Gaussians
from llrmpp_jax.model import fit_capacity, render

OUTPUTS = ("rgb", "depth")
# A browser camera can come closer than any input camera: room for this many times the most
# (Gaussian, block) slots an input camera needs at the render's size.
VIEW_HEADROOM = 2.0


def viewport_camera(fov_y: float, aspect: float, height: int, multiple: int) -> tuple[int, int, np.ndarray]:
    """``(height, width, intrinsics [4])`` of a render that fills a viewport exactly.

    ``fov_y`` is the viewport's vertical field of view (radians), ``aspect`` its width /
    height. The width is ``height * aspect`` rounded to a multiple of ``multiple`` (the
    model's size multiple); the focal lengths are set per axis so the image spans the
    viewport's full field of view in both directions, since the browser stretches it to
    the viewport (pixels are then very slightly non-square).
    """
    if not 0.0 < fov_y < math.pi or not aspect > 0.0:
        raise UserError(f"viewport_camera: need 0 < fov_y < pi and aspect > 0, got fov_y={fov_y}, aspect={aspect}")
    if height <= 0 or height % multiple:
        raise UserError(f"viewport_camera: height {height} must be a positive multiple of {multiple}")
    width = max(multiple, round(height * aspect / multiple) * multiple)
    t = math.tan(fov_y / 2.0)
    intrinsics = np.array([width / (2.0 * aspect * t), height / (2.0 * t), width / 2.0, height / 2.0], np.float32)
    return height, width, intrinsics


def _check_view(cfg: ModelConfig, output: str, partitions: int) -> None:
    if output not in OUTPUTS:
        raise UserError(f"output must be one of {OUTPUTS}, got {output!r}")
    most = cfg.decoder.partitions if cfg.head.mode == "feature" else 1
    if not 1 <= partitions <= most:
        raise UserError(f"partitions must be in [1, {most}] for this {cfg.head.mode}-mode model, got {partitions}")


def _with_partitions(params: dict, cfg: ModelConfig, s: int) -> tuple[dict, ModelConfig]:
    """The model restricted to its first ``s`` partition copies (see the module doc)."""
    if cfg.head.mode != "feature" or s == cfg.decoder.partitions:
        return params, cfg
    kernel = params["partition"]["kernel"]
    return {**params, "partition": {"kernel": kernel[:, :s]}}, replace(cfg, decoder=replace(cfg.decoder, partitions=s))


def render_view(
    params: dict,
    cfg: ModelConfig,
    gaussians: Gaussians,
    c2w: Float[Array, "4 4"],
    intrinsics: Float[Array, " 4"],
    height: int,
    width: int,
    output: str = "rgb",
    partitions: int | None = None,
) -> Float[Array, "H W C"]:
    """Render one camera of one scene: ``[H, W, 3]`` RGB in [0, 1] or ``[H, W, 1]`` depth.

    ``gaussians`` hold one scene (batch axis of size 1, as :func:`~llrmpp_jax.model.reconstruct`
    returns); ``c2w`` is OpenCV camera-to-world in the scene's (normalised) frame,
    ``intrinsics`` (fx, fy, cx, cy) in pixels of the ``height x width`` render.
    ``partitions`` defaults to the model's S. Depth is camera z in scene units; where the
    Gaussians leave a pixel empty (and the model has no depth head) it is 0.
    """
    s = cfg.decoder.partitions if partitions is None else partitions
    _check_view(cfg, output, s)
    if gaussians.means.shape[0] != 1:
        raise UserError(f"render_view: gaussians must hold one scene (batch 1), got batch {gaussians.means.shape[0]}")
    if output == "rgb" or "depth" in cfg.outputs:
        p, c = _with_partitions(params, cfg, s)
        out = render(p, c, gaussians, c2w[None, None], intrinsics[None, None], height, width, (output,))
        return out.images[output][0, 0]
    g = jax.tree.map(lambda a: a[0], gaussians)
    return splat_depth_view(g, cfg, (c2w, intrinsics), (height, width)).depth[:, :, None]


def display_image(image: Float[np.ndarray, "H W C"], output: str) -> np.ndarray:
    """A render as ``uint8 [H, W, 3]``: RGB clipped to [0, 1]; depth as inverse depth in
    grey (near = white), stretched between its 2nd and 98th percentiles over the pixels
    that have a depth (empty pixels black)."""
    image = np.asarray(image, np.float32)
    if output == "rgb":
        return np.round(np.clip(image, 0.0, 1.0) * 255.0).astype(np.uint8)
    depth = image[..., 0]
    valid = np.isfinite(depth) & (depth > 0.0)
    grey = np.zeros(depth.shape, np.float32)
    if valid.any():
        inv = 1.0 / depth[valid]
        lo, hi = np.percentile(inv, [2.0, 98.0])
        grey[valid] = np.clip((inv - lo) / max(hi - lo, 1e-12), 0.0, 1.0)
    return np.repeat(np.round(grey * 255.0).astype(np.uint8)[..., None], 3, axis=-1)


class ViewKey(NamedTuple):
    """What one compiled renderer is specialised to."""

    height: int
    width: int
    output: str
    partitions: int


@dataclasses.dataclass(frozen=True)
class Frame:
    """One rendered view: the raw render ``[H, W, C]``, the camera it was rendered at, and
    the seconds spent (``render_s`` device-synced, ``compile_s`` > 0 only on a first use)."""

    image: np.ndarray
    key: ViewKey
    c2w: np.ndarray
    intrinsics: np.ndarray
    render_s: float
    compile_s: float


class ViewRenderer:
    """:func:`render_view` for one scene, compiled once per :class:`ViewKey` and cached.

    Thread-safe for one caller at a time per instance (the viewer's render worker).
    """

    def __init__(
        self,
        params: dict,
        cfg: ModelConfig,
        gaussians: Gaussians,
        cameras: tuple[np.ndarray, np.ndarray, tuple[int, int]] | None = None,
    ):
        """``cameras``: ``(c2w [V, 4, 4], intrinsics [V, 4], (height, width))``, the scene's
        input cameras and the image size their intrinsics refer to; they size the splat
        buffer of each render size (module docstring). None: the config's buffer."""
        self.cfg = cfg
        self._params = jax.device_put(params)
        self._gaussians = jax.device_put(gaussians)
        self._cameras = cameras
        self._compiled: dict[ViewKey, jax.stages.Compiled] = {}
        self.compile_notes: dict[ViewKey, str] = {}  # how long each compile took, and whether from the cache

    def config_for(self, height: int, width: int) -> ModelConfig:
        """The config a ``height x width`` render compiles with: its splat buffer sized from
        the input cameras scaled to that size (module docstring)."""
        cfg = self.cfg
        if self._cameras is None or cfg.splat.max_intersections is not None:
            return cfg
        c2w, intrinsics, (h0, w0) = self._cameras
        scale = np.array([width / w0, height / h0, width / w0, height / h0], np.float32)
        k = np.asarray(intrinsics, np.float32) * scale
        default = cfg.splat.capacity(self._gaussians.means.shape[1], height, width)
        return fit_capacity(
            self._params,
            cfg,
            self._gaussians,
            jnp.asarray(c2w, jnp.float32)[None],
            jnp.asarray(k)[None],
            height,
            width,
            headroom=VIEW_HEADROOM,
            minimum=default,
        )

    @property
    def max_partitions(self) -> int:
        """The model's S (1 in colour mode)."""
        return self.cfg.decoder.partitions if self.cfg.head.mode == "feature" else 1

    def is_compiled(self, key: ViewKey) -> bool:
        return key in self._compiled

    def compile(self, key: ViewKey) -> float:
        """Compile the renderer for ``key`` if needed; returns the seconds it took (0 if cached)."""
        if key in self._compiled:
            return 0.0
        _check_view(self.cfg, key.output, key.partitions)
        t0 = time.perf_counter()
        fn = jax.jit(render_view, static_argnums=(1, 5, 6, 7, 8))
        cam = jax.ShapeDtypeStruct((4, 4), jnp.float32), jax.ShapeDtypeStruct((4,), jnp.float32)
        with CompileWatch() as watch:
            cfg = self.config_for(key.height, key.width)
            self._compiled[key] = fn.lower(
                self._params, cfg, self._gaussians, *cam, key.height, key.width, key.output, key.partitions
            ).compile()
        seconds = time.perf_counter() - t0
        self.compile_notes[key] = watch.describe(seconds)
        return seconds

    def render(self, key: ViewKey, c2w: np.ndarray, intrinsics: np.ndarray) -> Frame:
        """Render the camera ``(c2w [4, 4], intrinsics [4])`` at ``key`` (compiling on first use)."""
        compile_s = self.compile(key)
        c2w, intrinsics = np.asarray(c2w, np.float32), np.asarray(intrinsics, np.float32)
        t0 = time.perf_counter()
        image = np.asarray(jax.block_until_ready(self._compiled[key](self._params, self._gaussians, c2w, intrinsics)))
        return Frame(image, key, c2w, intrinsics, time.perf_counter() - t0, compile_s)

"""Frozen configuration dataclasses and presets.

Every architectural number the paper's ablation tables vary is a field here, so a
notebook changes one value with ``dataclasses.replace`` and gets a new model. Presets:

* :func:`paper_dl3dv` -- Long-LRM++ on DL3DV (paper §4.1): D=768, 24 blocks ``{1T7M}x3``,
  d_state 256, expand 2, headdim 64, p=8, K=16, F=32, r=2, decoder ``LLGGG`` E=256, S=2.
* :func:`long_lrm` -- the predecessor (colour Gaussians, ``mmmmmmmt``, token merge);
  :func:`long_lrm_i540` -- the same with its stage-3 Gaussian pruning.
* :func:`tiny` -- a model that runs forward in well under a second on one CPU core.
"""

from __future__ import annotations

import dataclasses
import math
import typing
from dataclasses import dataclass, field
from typing import Literal

from llrmpp_jax.errors import UserError
from llrmpp_jax.splat.config import SplatConfig

InterChunkSetting = Literal["auto", "associative", "sequential", "fused"]  # see Mamba2Config
# Global-attention kernels (nn.attention.multi_head_attention): see TransformerConfig.
AttentionImpl = Literal["xla", "cudnn", "blockwise", "splash"]
HeadMode = Literal["feature", "color"]  # see GaussianHeadConfig
Anchors = Literal["centre", "grid"]  # see GaussianHeadConfig
Primitive = Literal["3dgs", "2dgs"]  # see GaussianHeadConfig
SurfelDepth = Literal["center", "intersection"]  # see GaussianHeadConfig
Output = Literal["rgb", "depth"]  # the decoder's heads (ModelConfig.outputs)


@dataclass(frozen=True)
class Mamba2Config:
    """Long-LRM's bidirectional Mamba2 block (reference facts §1.4)."""

    d_state: int = 256
    d_conv: int = 4
    expand: int = 2
    headdim: int = 64
    ngroups: int = 1
    chunk_size: int = 256
    bidirectional: bool = True  # "bi": forward + reversed scan, outputs summed
    norm_eps: float = 1e-5
    # SSD's recurrence over chunk states (nn.ssd.ssd_scan): "associative" (log depth),
    # "sequential" (lax.scan over chunks; its backward holds one state per chunk, far less
    # than the associative form's), "fused" (one lax.scan doing each chunk's whole work: the
    # fastest on CPU; docs/results.md, "Selective scan (SSD) on CPU") or "auto"
    # (the default): "fused" on CPU, "sequential" on GPU and TPU (for_accelerators' choice),
    # see :meth:`resolved_inter_chunk`. All compute the same function; they differ in speed
    # and memory.
    inter_chunk: InterChunkSetting = "auto"
    # Run the two scan directions as a loop of two, each recomputed in the backward pass
    # (remat): the block's backward then holds one direction's activations, for one more
    # forward pass of the directions
    remat_directions: bool = False

    def __post_init__(self) -> None:
        if self.inter_chunk not in typing.get_args(InterChunkSetting):
            raise UserError(
                "Mamba2Config.inter_chunk must be 'auto', 'associative', 'sequential' or 'fused', "
                f"got {self.inter_chunk!r}"
            )
        if self.chunk_size < 1:
            raise UserError(f"Mamba2Config.chunk_size must be >= 1, got {self.chunk_size}")

    def resolved_inter_chunk(self, backend: str | None = None) -> str:
        """The SSD form to run on ``backend`` (default ``jax.default_backend()``): ``"auto"``
        is ``"fused"`` on ``"cpu"`` (the fastest there) and ``"sequential"`` elsewhere (the
        least memory at the paper's lengths); any other value as it is."""
        if self.inter_chunk != "auto":
            return self.inter_chunk
        if backend is None:
            import jax

            backend = jax.default_backend()
        return "fused" if backend == "cpu" else "sequential"

    def d_inner(self, d_model: int) -> int:
        return self.expand * d_model

    def nheads(self, d_model: int) -> int:
        d_inner = self.d_inner(d_model)
        if d_inner % self.headdim:
            raise UserError(
                f"Mamba2Config: d_inner={d_inner} (expand*d_model) is not a multiple of headdim={self.headdim}"
            )
        return d_inner // self.headdim


@dataclass(frozen=True)
class TransformerConfig:
    """Pre-LN transformer block: LayerNorm without bias, MLP ratio 4, exact GELU, no biases."""

    head_dim: int = 64
    mlp_ratio: int = 4
    qk_norm: bool = True  # RMSNorm per head on q and k (LVSM); Long-LRM itself has none
    norm_eps: float = 1e-5
    # Global-attention kernel (nn.attention.multi_head_attention): "blockwise" is
    # FlashAttention-2 in pure JAX (any backend and dtype, memory linear in L, the default);
    # "cudnn" the cuDNN flash kernel (NVIDIA GPU; computes in bf16, wider inputs are cast;
    # for_accelerators picks it there); "splash" the Pallas TPU splash-attention kernel (TPU, or
    # Pallas's interpret mode elsewhere; for_accelerators picks it on TPU); "xla" materialises
    # [nh, L, L] logits (quadratic memory: short L only).
    attention_impl: AttentionImpl = "blockwise"
    attention_block_q: int = 512  # blockwise, splash: queries per block (splash: rounded up to 128s)
    attention_block_k: int = 512  # blockwise, splash: keys per block (logits block [nh, bq, bk])

    def __post_init__(self) -> None:
        if self.attention_impl not in typing.get_args(AttentionImpl):
            raise UserError(
                f"TransformerConfig.attention_impl must be 'xla', 'cudnn', 'blockwise' or 'splash', "
                f"got {self.attention_impl!r}"
            )
        if self.attention_block_q < 1 or self.attention_block_k < 1:
            raise UserError(
                f"TransformerConfig: attention block sizes must be >= 1, got "
                f"attention_block_q={self.attention_block_q}, attention_block_k={self.attention_block_k}"
            )


@dataclass(frozen=True)
class BackboneConfig:
    """Input tokenizer + block stack.

    ``pattern`` uses ``T`` (transformer) and ``M`` (Mamba2), case-insensitive, with
    ``{...}xN`` repetition: ``"{1T7M}x3"`` = T M M M M M M M, three times. A pattern
    shorter than ``num_layers`` is tiled (Long-LRM's ``"mmmmmmmt"`` tiled to 24).
    ``dims`` has one entry per stage; token merges (Long-LRM) happen before the block
    indices in ``merge_layers`` and move to the next width.
    """

    dims: tuple[int, ...] = (768,)
    pattern: str = "{1T7M}x3"
    num_layers: int = 24
    merge_layers: tuple[int, ...] = ()
    num_global_tokens: int = 2
    mamba: Mamba2Config = field(default_factory=Mamba2Config)
    transformer: TransformerConfig = field(default_factory=TransformerConfig)
    # recompute each block's activations in the backward pass; the blocks then run as loops
    # over the pattern (nn.remat_loops.remat_blocks) so that the backward holds one block's
    # activations at a time
    remat: bool = False

    def __post_init__(self) -> None:
        if len(self.dims) != len(self.merge_layers) + 1:
            raise UserError(
                f"BackboneConfig: dims has {len(self.dims)} entries but merge_layers "
                f"{self.merge_layers} needs {len(self.merge_layers) + 1}"
            )


def from_dict(cls: type, data: dict):
    """Rebuild a (nested) config dataclass from ``dataclasses.asdict`` output read back
    from JSON (lists become tuples). ``ValueError`` naming an unknown field."""
    hints = typing.get_type_hints(cls)
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(data) - names)
    if unknown:
        raise UserError(f"{cls.__name__}: unknown field(s) {unknown}")
    kwargs = {}
    for name, value in data.items():
        kind = hints[name]
        if dataclasses.is_dataclass(kind):
            value = from_dict(kind, value)  # pyright: ignore[reportArgumentType] -- is_dataclass of a type hint: a dataclass type
        elif isinstance(value, list):
            value = tuple(tuple(v) if isinstance(v, list) else v for v in value)
        kwargs[name] = value
    return cls(**kwargs)


@dataclass(frozen=True)
class GaussianHeadConfig:
    """Per-token Gaussian prediction (paper §3.2; activations from Long-LRM, facts §1.6).

    ``mode="feature"``: K Gaussians per token, each with an F-dim feature, a 2D pixel
    offset from the patch centre, a distance along its ray, quaternion (wxyz), opacity
    and log-scale. ``mode="color"`` (Long-LRM): one Gaussian per pixel with SH colour of
    degree ``sh_degree``, positioned on its own pixel ray.

    ``primitive="2dgs"`` (colour mode only): the Long-LRM 2DGS row of the paper's Table 7
    ("Long-LRM with a 2D Gaussian head", Huang et al. 2024): the same colour head with two
    log-scales per Gaussian instead of three, rendered as planar disks by the 2DGS splatter
    (``splat.rasterize(..., primitive="2dgs")``), whose depth is each surfel's centre z
    (``surfel_depth`` None or ``"center"``, gsplat's ``rasterization_2dgs``) or the ray-splat
    intersection's z (``"intersection"``, the 2DGS paper's rasterizer).
    """

    mode: HeadMode = "feature"
    gaussians_per_token: int = 16  # K (feature mode)
    feature_dim: int = 32  # F (feature mode)
    sh_degree: int = 3  # color mode
    # Offsets from the patch centre, in pixels: offset_scale * tanh(raw) * patch_size (at most
    # offset_scale patch widths), or raw * patch_size, unbounded, with offset_scale=None (the
    # paper's "move freely"). Bounded by default, so no Gaussian leaves the screen early in
    # training; unbounding it made no measurable difference (docs/lab-notes.md,
    # "The Gaussians' offset bound").
    offset_scale: float | None = 1.0
    # Where a token's K Gaussians start: "centre" (all at the patch centre, every head column
    # drawn: Long-LRM++'s head as the paper describes it) or "grid" (K = m*m on the cell
    # centres of an m x m split of the patch, with the head's offset, distance, rotation and
    # log-scale columns starting at zero: isotropic, one size, at max_dist / 2; see
    # gaussians.head_kernel_init). The paper says only that they "move freely"; its K = 16 at a
    # 4x4-pixel canvas footprint per token is one Gaussian per canvas pixel, where "grid"
    # starts. The demo and small recipes use "grid": with "centre" a patch's Gaussians cover
    # each other and the canvas carries little more than its mean (docs/lab-notes.md, "Fourth round").
    anchors: Anchors = "centre"
    max_dist: float = 500.0  # distance = sigmoid(raw) * max_dist (scene units)
    scale_bias: float = -6.9  # log-scale = min(raw + bias, scale_max)
    scale_max: float = -1.2
    opacity_bias: float = -2.0  # opacity = sigmoid(raw + bias)
    # Long-LRM's pruning (colour mode, pruning.py), in training and evaluation: keep
    # 1 - prune_ratio of the Gaussians, prune_random_ratio of those at random, the rest the
    # most opaque. Its stage 3 (960x540, the released checkpoint) uses 0.6 / 0.1; 0: none.
    prune_ratio: float = 0.0
    prune_random_ratio: float = 0.0
    # Std of the head's linear weights: Long-LRM's normal(0.02), or None for 1/sqrt(fan-in)
    # (LeCun normal). At the paper's widths (768-1024) they are within 1.6x; at the width of
    # the CPU models (64) 0.02 is 8x smaller, and the chain of linear maps from head through
    # splat to decoder output learns slowly (docs/lab-notes.md, "Second round").
    init_std: float | None = 0.02
    primitive: Primitive = "3dgs"  # "2dgs": two scales, planar disks (colour mode; class doc)
    surfel_depth: SurfelDepth | None = None  # 2dgs: "center" (None) or "intersection"

    def __post_init__(self) -> None:
        if self.mode not in typing.get_args(HeadMode):
            raise UserError(f"GaussianHeadConfig.mode must be 'feature' or 'color', got {self.mode!r}")
        self._check_primitive()
        if self.anchors not in typing.get_args(Anchors):
            raise UserError(f"GaussianHeadConfig.anchors must be 'centre' or 'grid', got {self.anchors!r}")
        if self.anchors == "grid" and math.isqrt(self.gaussians_per_token) ** 2 != self.gaussians_per_token:
            raise UserError(
                "GaussianHeadConfig: anchors='grid' needs a square gaussians_per_token (4, 9, 16, ...), "
                f"got {self.gaussians_per_token}"
            )
        if not 0 <= self.prune_ratio < 1 or not 0 <= self.prune_random_ratio <= 1:
            raise UserError(
                f"GaussianHeadConfig: need 0 <= prune_ratio < 1 and 0 <= prune_random_ratio <= 1, got "
                f"{self.prune_ratio} and {self.prune_random_ratio}"
            )
        if self.prune_ratio and self.mode != "color":
            raise UserError(
                f"GaussianHeadConfig: pruning is Long-LRM's colour-mode recipe; mode={self.mode!r} needs prune_ratio=0"
            )

    def _check_primitive(self) -> None:
        """One line naming the setting that a 2D Gaussian head cannot honour."""
        if self.primitive not in typing.get_args(Primitive):
            raise UserError(f"GaussianHeadConfig.primitive must be '3dgs' or '2dgs', got {self.primitive!r}")
        if self.primitive == "3dgs":
            if self.surfel_depth is not None:
                raise UserError(
                    f"GaussianHeadConfig.surfel_depth={self.surfel_depth!r} is for primitive='2dgs'; "
                    "primitive='3dgs' needs surfel_depth=None"
                )
            return
        if self.surfel_depth not in (None, *typing.get_args(SurfelDepth)):
            raise UserError(
                f"GaussianHeadConfig.surfel_depth must be 'center', 'intersection' or None, got {self.surfel_depth!r}"
            )
        if self.mode != "color":
            raise UserError(
                f"GaussianHeadConfig: primitive='2dgs' is Long-LRM's colour head with 2D Gaussians; "
                f"mode={self.mode!r} needs primitive='3dgs'"
            )
        if not 0 <= self.sh_degree <= 3:
            raise UserError(f"GaussianHeadConfig: primitive='2dgs' supports sh_degree 0..3, got {self.sh_degree}")

    @property
    def num_scales(self) -> int:
        """Scales per Gaussian: 3 (3D Gaussians) or 2 (2D Gaussians' tangent axes)."""
        return 2 if self.primitive == "2dgs" else 3

    @property
    def splat_surfel_depth(self) -> str | None:
        """``surfel_depth`` of :func:`llrmpp_jax.splat.rasterize` for this head's Gaussians
        (with ``primitive=self.primitive``): None for 3D Gaussians, else ``"center"`` unless
        ``"intersection"`` was asked for."""
        return None if self.primitive == "3dgs" else (self.surfel_depth or "center")


@dataclass(frozen=True)
class DecoderConfig:
    """Target-frame decoder (paper §3.3): canvas (H/r, W/r) -> patchify to (H/8, W/8)."""

    canvas_ratio: int = 2  # r
    token_stride: int = 8  # q: tokens are (H/q, W/q); canvas patch = q / r
    dim: int = 256  # E
    blocks: str = "LLGGG"  # L = local k-NN attention, G = global attention
    num_neighbours: int = 64  # k
    partitions: int = 2  # S (1 = no partitioning)
    # Add a fixed 2-D sin-cos embedding of the token coordinates after the tokenizer: the
    # paper's Table 5 "GGG" baseline (global attention with absolute positions); needs dim % 4 == 0.
    absolute_positions: bool = False
    transformer: TransformerConfig = field(default_factory=TransformerConfig)
    remat: bool = False
    # Std of the tokenizer, merge and output-head weights: normal(0.02) as Long-LRM's linear
    # layers, or None for 1/sqrt(fan-in) (LeCun normal; see GaussianHeadConfig.init_std).
    init_std: float | None = 0.02
    # Log-depth offset of the depth head: depth = exp(head(x) + depth_bias) (scene units).
    # The head is bias-free, so with 0 every depth starts at exp(0) = 1 unit and the shared
    # decoder must bend its features to reach the data's depths, at the expense of RGB and of
    # depth itself (docs/lab-notes.md, "The decoder's depth head on one scene"). Set it near
    # the log of the training data's typical depth, as Long-LRM's Gaussian head sets
    # scale_bias and opacity_bias.
    depth_bias: float = 0.0

    def __post_init__(self) -> None:
        if self.absolute_positions and self.dim % 4:
            raise UserError(f"DecoderConfig: absolute_positions needs dim % 4 == 0, got dim={self.dim}")
        if self.token_stride % self.canvas_ratio:
            raise UserError(
                f"DecoderConfig: token_stride {self.token_stride} must be a multiple of "
                f"canvas_ratio {self.canvas_ratio}"
            )
        if self.partitions < 1:
            raise UserError(f"DecoderConfig.partitions must be >= 1, got {self.partitions}")


@dataclass(frozen=True)
class ModelConfig:
    """The whole model. ``outputs`` lists the heads trained and rendered ("rgb", "depth")."""

    patch_size: int = 8
    backbone: BackboneConfig = field(default_factory=BackboneConfig)
    head: GaussianHeadConfig = field(default_factory=GaussianHeadConfig)
    decoder: DecoderConfig = field(default_factory=DecoderConfig)
    splat: SplatConfig = field(default_factory=SplatConfig)
    outputs: tuple[Output, ...] = ("rgb",)
    background: tuple[float, float, float] = (1.0, 1.0, 1.0)  # colour mode only (Long-LRM: white)

    def __post_init__(self) -> None:
        if (
            self.head.mode == "feature"
            and self.decoder.token_stride % self.patch_size
            and self.patch_size % self.decoder.token_stride
        ):
            raise UserError(
                f"ModelConfig: decoder token_stride {self.decoder.token_stride} and patch_size "
                f"{self.patch_size} must divide one another"
            )

    @property
    def token_stride(self) -> int:
        """Input pixels per backbone token side after all merges."""
        return self.patch_size * 2 ** len(self.backbone.merge_layers)

    @property
    def size_multiple(self) -> int:
        """Image sides must be multiples of this (tokens, merges and decoder patches)."""
        return math.lcm(self.token_stride, self.decoder.token_stride)


def for_accelerators(model: ModelConfig, backend: str | None = None) -> ModelConfig:
    """Memory-efficient attention in every global-attention block, remat everywhere (the
    Mamba2 blocks' two directions included) and the SSD's sequential inter-chunk
    recurrence (its backward holds one chunk state per chunk, where the associative scan's
    holds several copies of the full-size state).

    ``backend`` (default ``jax.default_backend()``): on ``"gpu"`` the cuDNN flash kernel
    (``attention_impl="cudnn"``, meant for bf16 runs: it computes in bf16, casting float32
    q, k, v; much faster than the blockwise kernel: docs/results.md, "Global attention on
    one H200"), on ``"tpu"`` the Pallas splash-attention kernel (``"splash"``, written for the
    TPU's matrix unit; bf16 or float32), anywhere else (CPU) the pure-JAX blockwise kernel,
    which needs no vendor library and works in any dtype. XLA's plain attention would hold
    [heads, L, L] scores (L = 261K backbone tokens at stage 4: over a TiB per block).
    """
    if backend is None:
        import jax

        backend = jax.default_backend()
    model = with_attention(model, {"gpu": "cudnn", "tpu": "splash"}.get(backend, "blockwise"))
    return dataclasses.replace(
        model,
        backbone=dataclasses.replace(
            model.backbone,
            remat=True,
            mamba=dataclasses.replace(model.backbone.mamba, inter_chunk="sequential", remat_directions=True),
        ),
        decoder=dataclasses.replace(model.decoder, remat=True),
    )


def with_attention(model: ModelConfig, impl: str, block: tuple[int, int] | None = None) -> ModelConfig:
    """``model`` with ``impl`` as the global-attention kernel of the backbone's and the
    decoder's transformers and, given ``block`` (queries, keys), the blockwise kernel's blocks."""

    def kernel(t: TransformerConfig) -> TransformerConfig:
        t = dataclasses.replace(t, attention_impl=impl)
        return dataclasses.replace(t, attention_block_q=block[0], attention_block_k=block[1]) if block else t

    return dataclasses.replace(
        model,
        backbone=dataclasses.replace(model.backbone, transformer=kernel(model.backbone.transformer)),
        decoder=dataclasses.replace(model.decoder, transformer=kernel(model.decoder.transformer)),
    )


def paper_dl3dv() -> ModelConfig:
    """Long-LRM++ on DL3DV (paper §4.1): ~110M parameters (backbone ~104M, decoder ~4M)."""
    return ModelConfig()


# Where paper_scannet's depth head starts (DecoderConfig.depth_bias): log 4, i.e. 4 scene units,
# the typical target depth of the scannet recipe's first stage, the one that trains the head
# from its start. An estimate, not a measurement (no ScanNet data was at hand): the recipe
# trains in Long-LRM's normalised units (geometry.normalize_scene: the input cameras put in
# [-1, 1]^3, depths scaled with them), so a depth of d metres is d / e units, e the
# largest |coordinate| of the 8 input cameras about their mean; a stage-1 window is 64-128 frames,
# 2-4 s of ScanNet's 30 Hz stream, which a hand-held scan at ~0.3 m/s crosses in ~1 m, so
# e ~ 0.5 m; ScanNet's indoor depths have a median near 2 m (rooms filmed from 1-4 m away);
# 2 / 0.5 = 4. Measure the mean log target depth of stage-1 batches on the real data and set
# it here. Later stages see whole sequences (e of metres, depths near 1 unit); by then the
# head has learnt the scale, the bias only places its start.
SCANNET_DEPTH_BIAS = math.log(4.0)


def paper_scannet() -> ModelConfig:
    """Long-LRM++ on ScanNetv2: the DL3DV architecture with colour and depth heads, the
    depth head starting at 4 scene units (:data:`SCANNET_DEPTH_BIAS`)."""
    return ModelConfig(outputs=("rgb", "depth"), decoder=DecoderConfig(depth_bias=SCANNET_DEPTH_BIAS))


def long_lrm() -> ModelConfig:
    """Long-LRM (the predecessor, facts §1.1): colour Gaussians, dims [256, 1024], merge at 8."""
    return ModelConfig(
        backbone=BackboneConfig(
            dims=(256, 1024),
            pattern="mmmmmmmt",
            num_layers=24,
            merge_layers=(8,),
            transformer=TransformerConfig(qk_norm=False),
        ),
        head=GaussianHeadConfig(mode="color"),
    )


def long_lrm_i540() -> ModelConfig:
    """Long-LRM's stage 3 at 960x540 (``dl3dv_i540_32input_8target.yaml``, the released
    checkpoint): :func:`long_lrm` with Gaussian pruning 0.6 / random 0.1 (facts §1.6)."""
    base = long_lrm()
    return dataclasses.replace(base, head=dataclasses.replace(base.head, prune_ratio=0.6, prune_random_ratio=0.1))


def tiny() -> ModelConfig:
    """A feature-Gaussian model small enough for CPU tests and the demo (~0.3M params)."""
    return ModelConfig(
        backbone=BackboneConfig(
            dims=(64,),
            pattern="{1T3M}x1",
            num_layers=4,
            mamba=Mamba2Config(d_state=16, headdim=16, chunk_size=64),
            transformer=TransformerConfig(head_dim=16),
        ),
        head=GaussianHeadConfig(gaussians_per_token=4, feature_dim=16),
        decoder=DecoderConfig(dim=64, blocks="LG", num_neighbours=16, transformer=TransformerConfig(head_dim=16)),
    )

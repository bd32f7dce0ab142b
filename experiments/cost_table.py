"""Where a paper-scale step's time should go, computed on a CPU before any accelerator run.

Run:  taskset -c 1 python experiments/cost_table.py          # ~1 min on one core; writes
      experiments/results/cost_table.json and prints the Markdown tables
      python experiments/cost_table.py --only global_attention,ssd_scan --out /tmp/t.json

1. **Components** of the paper model (``config.paper_dl3dv()``) at the stage-4 shapes (32
   inputs + 8 targets at 544x960: L = 261,122 backbone tokens, N = 4,177,920 Gaussians,
   one 272x480 canvas per target, S = 2 partition copies), each lowered *alone* from
   ``jax.ShapeDtypeStruct`` s and compiled for the CPU (nothing is allocated; every piece
   compiles whole in seconds and < 1 GB, so none is scaled down), in the dtype a bf16
   training step runs it: XLA's ``cost_analysis()`` of the compiled piece gives ``flops``
   and ``bytes`` accessed, and the H100 roofline lower bound is ``max(flops / peak,
   bytes / 3.35e12)`` seconds (HBM3 bandwidth; peak 989e12 for pieces whose products run in
   bf16, 494.5e12 for float32 ones, which XLA:GPU runs as TF32; for the global attention
   the bytes of q, k, v and the output alone, ``roofline_gbytes``). ``per_step`` is how many
   times a stage-4 step's *forward* runs the piece (the backward adds ~2x for the matrix
   products); ``step_forward_ms`` = per_step x roofline.
   Compiled, not lowered: the lowered module's bytes count every elementwise op's operands
   before fusion (716 GB for the transformer linears, from the exact GELU's polynomial)
   and its FLOPs charge the splat binning's ``cumsum`` (a ``reduce_window``) its window
   times its length (1.1e15); XLA:CPU's passes rewrite both. Caveats, in the rows' ``note``:
   XLA counts a ``while`` body once (the splat composite's loops); the plain attention's
   bytes include the [heads, L, L] logits a flash kernel (cuDNN) never writes; XLA:CPU
   computes bf16 matrix products in float32, and the converts it adds make the bytes of
   the bf16 pieces an overestimate for a GPU (up to ~4x for the backbone's linears).
2. **Programs**: matrix-multiply FLOPs (``benchmarks.measure.matmul_flops``, tracing only, no
   recomputation) of reconstruct at 16/32/64 inputs, one render and the stage-4 step's
   forward + backward, the seconds they take at the H100's peak, and the paper's A100
   times: the efficiency each implies.
"""

from __future__ import annotations

import argparse
import json
import os
from collections.abc import Callable
from dataclasses import dataclass, replace

import jax
import jax.numpy as jnp

from llrmpp_jax import config as C
from llrmpp_jax.benchmarks.measure import PEAK_BF16_TFLOPS, markdown_table, matmul_flops, xla_cost
from llrmpp_jax.benchmarks.paper import PAPER_A100, counting_config, train_step_model_flops
from llrmpp_jax.benchmarks.paper_step import paper_stage4_experiment
from llrmpp_jax.convert.vgg import vgg_layers
from llrmpp_jax.gaussians import GaussianHead, Gaussians
from llrmpp_jax.losses import perceptual_loss
from llrmpp_jax.model import init_params, reconstruct, render
from llrmpp_jax.nn.attention import multi_head_attention
from llrmpp_jax.nn.ssd import ssd_scan
from llrmpp_jax.nn.transformer import TransformerBlock
from llrmpp_jax.splat.binning import bin_gaussians
from llrmpp_jax.splat.composite import composite
from llrmpp_jax.splat.projection import project_gaussians

H100_FLOPS = PEAK_BF16_TFLOPS["H100"] * 1e12
# Float32 matrix products run on the tensor cores as TF32 (XLA:GPU's default precision,
# docs/lab-notes.md "On an H200"): half the bf16 rate.
H100_TF32_FLOPS = H100_FLOPS / 2
H100_BYTES_PER_S = 3.35e12  # H100 SXM HBM3
CFG = C.paper_dl3dv()
V, T, H, W = 32, 8, 544, 960  # stage 4
P, D = CFG.patch_size, CFG.backbone.dims[0]
GRID = (H // P, W // P)
TOKENS = V * GRID[0] * GRID[1]
L = TOKENS + CFG.backbone.num_global_tokens
N = TOKENS * CFG.head.gaussians_per_token
HC, WC = H // CFG.decoder.canvas_ratio, W // CFG.decoder.canvas_ratio
S = CFG.decoder.partitions
F = CFG.head.feature_dim
BF16, F32 = jnp.bfloat16, jnp.float32
MAMBA = CFG.backbone.mamba
NH_M, D_INNER = MAMBA.nheads(D), MAMBA.d_inner(D)
IN_PROJ = 2 * D_INNER + 2 * MAMBA.ngroups * MAMBA.d_state + NH_M
LAYOUT_T, LAYOUT_M = 3, 21  # "{1T7M}x3"
DEC_GRID = (
    HC * CFG.decoder.canvas_ratio // CFG.decoder.token_stride,
    WC * CFG.decoder.canvas_ratio // CFG.decoder.token_stride,
)


def sds(*shape: int, dtype=F32) -> jax.ShapeDtypeStruct:
    return jax.ShapeDtypeStruct(shape, dtype)


@dataclass(frozen=True)
class Piece:
    """One component: ``build()`` -> ``(fn, args)`` (shape structs); ``per_step`` runs in a
    stage-4 step's forward; ``shape`` and ``note`` for the table."""

    name: str
    shape: str
    per_step: int
    build: Callable[[], tuple[Callable, tuple]]
    bf16: bool  # its matrix products in bf16 (peak 989 TFLOP/s), else float32 (TF32, 494.5)
    note: str = ""
    # The roofline's bytes are the piece's arguments and results alone: a flash kernel
    # keeps the plain kernel's [heads, L, L] logits on chip.
    io_bytes_only: bool = False


def _transformer_linears():
    def fn(x, wqkv, wo, w1, w2):  # the block's matrix products around its attention
        qkv = x @ wqkv
        return qkv[..., :D] @ wo + jax.nn.gelu(x @ w1, approximate=False) @ w2

    return fn, (
        sds(1, L, D, dtype=BF16),
        sds(D, 3 * D, dtype=BF16),
        sds(D, D, dtype=BF16),
        sds(D, 4 * D, dtype=BF16),
        sds(4 * D, D, dtype=BF16),
    )


def _mamba_linears():
    def fn(x, w_in, w_out):  # the shared in/out projections of both scan directions
        return (x @ w_in)[..., :D_INNER] @ w_out

    return fn, (sds(1, L, D, dtype=BF16), sds(D, IN_PROJ, dtype=BF16), sds(D_INNER, D, dtype=BF16))


def _global_attention():
    def fn(q, k, v):
        return multi_head_attention(q, k, v, implementation="xla")

    nh, hd = D // CFG.backbone.transformer.head_dim, CFG.backbone.transformer.head_dim
    return fn, (sds(1, L, nh, hd, dtype=BF16), sds(1, L, nh, hd, dtype=BF16), sds(1, L, nh, hd, dtype=BF16))


def _ssd():
    hd, n = MAMBA.headdim, MAMBA.d_state

    def fn(x, dt, a, b, c, d):
        return ssd_scan(x, dt, a, b, c, chunk_size=MAMBA.chunk_size, D=d, inter_chunk="associative")

    return fn, (
        sds(1, L, NH_M, hd, dtype=BF16),
        sds(1, L, NH_M),
        sds(NH_M),
        sds(1, L, 1, n, dtype=BF16),
        sds(1, L, 1, n, dtype=BF16),
        sds(NH_M),
    )


def _gaussian_head():
    head = GaussianHead(CFG.head, CFG.token_stride)
    args = (sds(1, TOKENS, D, dtype=BF16), sds(1, V, 4, 4), sds(1, V, 4))
    params = jax.eval_shape(lambda t, c, k: head.init(jax.random.key(0), t, GRID, c, k), *args)["params"]
    params = jax.tree.map(lambda x: sds(*x.shape, dtype=BF16), params)
    return (lambda p, t, c, k: head.apply({"params": p}, t, GRID, c, k)), (params, *args)


def _project(means, quats, scales, c2w, intrinsics):
    return project_gaussians(means, quats, scales, c2w, intrinsics, HC, WC, CFG.splat)


GAUSSIANS = (sds(N, 3), sds(N, 4), sds(N, 3), sds(4, 4), sds(4))  # means, quats, scales; one camera
CAPACITY = CFG.splat.capacity(N, HC, WC)


def _bin(projected, opacities):
    return bin_gaussians(projected, HC, WC, CAPACITY, CFG.splat, opacities=opacities)


def _splat_projection():
    return _project, GAUSSIANS


def _splat_binning():
    return _bin, (jax.eval_shape(_project, *GAUSSIANS), sds(N))


def _splat_composite():
    proj = jax.eval_shape(_project, *GAUSSIANS)
    bins = jax.eval_shape(_bin, proj, sds(N))

    def fn(means2d, quad_form, opacities, features, bins):  # one copy: F features + depth
        return composite(means2d, quad_form, opacities, features, bins, HC, WC, CFG.splat)

    return fn, (proj.means2d, proj.quad_form, sds(N), sds(N, F + 1), bins)


def _decoder_block(kind: str):
    def build():
        dcfg = CFG.decoder
        block = TransformerBlock(
            dim=dcfg.dim,
            cfg=replace(dcfg.transformer, attention_impl="xla"),
            attention=kind,  # pyright: ignore[reportArgumentType] -- a str checked against the Literal's values at run time
            grid=DEC_GRID,
            num_neighbours=dcfg.num_neighbours,
        )
        x = sds(S, DEC_GRID[0] * DEC_GRID[1], dcfg.dim)  # the S copies of one target, float32 as it runs
        params = jax.eval_shape(lambda x: block.init(jax.random.key(0), x), x)["params"]
        return (lambda p, x: block.apply({"params": p}, x)), (params, x)

    return build


def _vgg19() -> dict:
    """Long-LRM's VGG19 perceptual net's parameters (conv1_1..conv5_2) as shape structs."""
    return {
        name: {"kernel": sds(3, 3, cin, cout), "bias": sds(cout)} for name, _, cin, cout in vgg_layers("vgg19")[:14]
    }


def _vgg_loss():
    return perceptual_loss, (_vgg19(), sds(T, H, W, 3), sds(T, H, W, 3))


PIECES = (
    Piece(
        "backbone_transformer_linears",
        f"[1, {L}, {D}] bf16: qkv, out, MLP 4x",
        LAYOUT_T,
        _transformer_linears,
        bf16=True,
    ),
    Piece(
        "backbone_mamba_linears",
        f"[1, {L}, {D}] bf16: in {IN_PROJ}, out {D_INNER}->{D}",
        LAYOUT_M,
        _mamba_linears,
        bf16=True,
    ),
    Piece(
        "global_attention",
        f"[1, {L}, 12, 64] bf16, plain XLA softmax(QK^T)V",
        LAYOUT_T,
        _global_attention,
        bf16=True,
        io_bytes_only=True,
        note="XLA's bytes are the plain kernel's, [12, L, L] logits included; the roofline takes q, k, v and "
        "the output alone, as a flash kernel (cuDNN) moves them",
    ),
    Piece(
        "ssd_scan",
        f"one direction, [1, {L}, {NH_M}, {MAMBA.headdim}], d_state {MAMBA.d_state}, chunk {MAMBA.chunk_size}",
        2 * LAYOUT_M,
        _ssd,
        bf16=False,
        note="associative inter-chunk form (no loop); the GPU runs the sequential one",
    ),
    Piece("gaussian_head", f"[1, {TOKENS}, {D}] bf16 -> {N} Gaussians (K=16, F={F})", 1, _gaussian_head, bf16=True),
    Piece("splat_projection", f"{N} Gaussians -> {HC}x{WC} canvas", T, _splat_projection, bf16=False),
    Piece("splat_binning_sort", f"{N} Gaussians, capacity {CAPACITY}", T, _splat_binning, bf16=False),
    Piece(
        "splat_composite",
        f"one copy of {N} Gaussians, {F}+1 channels, {HC}x{WC}",
        T * S,
        _splat_composite,
        bf16=False,
        note="while loops over tile groups: XLA counts one body, a lower bound",
    ),
    Piece(
        "decoder_local_block",
        f"[{S}, {DEC_GRID[0] * DEC_GRID[1]}, 256] f32, k=64 + MLP",
        2 * T,
        _decoder_block("local"),
        bf16=False,
    ),
    Piece(
        "decoder_global_block",
        f"[{S}, {DEC_GRID[0] * DEC_GRID[1]}, 256] f32, 4 heads + MLP",
        3 * T,
        _decoder_block("global"),
        bf16=False,
        note="plain attention: bytes include its [2, 4, L, L] float32 logits (2.1 GB)",
    ),
    Piece("vgg19_loss", f"{T} predictions + {T} targets at {H}x{W} f32, conv1_1..conv5_2", 1, _vgg_loss, bf16=False),
)


def measure(piece: Piece) -> dict:
    """Compile ``piece`` for the CPU (from shape structs) and read XLA's cost analysis."""
    fn, args = piece.build()
    compiled = jax.jit(fn).lower(*args).compile()
    cost = xla_cost(compiled)
    flops, nbytes = cost["flops"], cost["bytes_accessed"]
    io = compiled.memory_analysis()
    roof_bytes = io.argument_size_in_bytes + io.output_size_in_bytes if piece.io_bytes_only else nbytes  # pyright: ignore[reportOptionalMemberAccess] -- memory_analysis() is None only on a backend without it; CPU, GPU and TPU have it
    peak = H100_FLOPS if piece.bf16 else H100_TF32_FLOPS
    roof_s = max(flops / peak, roof_bytes / H100_BYTES_PER_S)  # pyright: ignore[reportOptionalOperand] -- XLA's cost analysis has flops and bytes for these programs
    notes = [piece.note] + (
        ["bytes: XLA:CPU's, with float32 copies of the bf16 operands (an overestimate)"]
        if piece.bf16 and not piece.io_bytes_only
        else []
    )
    return {
        "name": piece.name,
        "shape": piece.shape,
        "per_step": piece.per_step,
        "bf16": piece.bf16,
        "gflops": flops / 1e9,  # pyright: ignore[reportOptionalOperand] -- as above
        "gbytes": nbytes / 1e9,  # pyright: ignore[reportOptionalOperand] -- as above
        "roofline_gbytes": roof_bytes / 1e9,  # pyright: ignore[reportOptionalOperand] -- as above
        "intensity_flops_per_byte": flops / roof_bytes,  # pyright: ignore[reportOperatorIssue] -- as above
        "h100_roofline_ms": 1e3 * roof_s,
        "bound": "compute" if flops / peak >= roof_bytes / H100_BYTES_PER_S else "memory",  # pyright: ignore[reportOptionalOperand] -- as above
        "step_forward_ms": 1e3 * roof_s * piece.per_step,
        "note": "; ".join(n for n in notes if n),
    }


def programs() -> list[dict]:
    """Matrix-multiply FLOPs of the whole programs (tracing only) and what they imply."""
    cfg = counting_config(CFG)
    params = jax.eval_shape(lambda k: init_params(k, cfg, 2, 32, 32), jax.random.key(0))
    bf = jax.tree.map(lambda x: sds(*x.shape, dtype=BF16), params)
    rows = []
    for v in (16, 32, 64):
        args = (bf, sds(1, v, H, W, 3), sds(1, v, 4, 4), sds(1, v, 4))
        rows.append(
            (
                f"reconstruct {v} views",
                matmul_flops(lambda p, i, c, k: reconstruct(p, cfg, i, c, k), *args),
                PAPER_A100["reconstruct_s"][v],
            )
        )
    g = Gaussians(sds(1, N, 3), sds(1, N, 4), sds(1, N, 3), sds(1, N), sds(1, N, F))  # pyright: ignore[reportArgumentType] -- shapes only: traced, never computed
    rows.append(
        (
            "render one target",
            matmul_flops(lambda p, g, c, k: render(p, cfg, g, c, k, H, W).images, bf, g, sds(1, 1, 4, 4), sds(1, 1, 4)),
            1 / PAPER_A100["render_fps"],
        )
    )
    exp, _ = paper_stage4_experiment()
    batch = {
        "input_images": sds(1, V, H, W, 3),
        "input_c2w": sds(1, V, 4, 4),
        "input_intrinsics": sds(1, V, 4),
        "target_images": sds(1, T, H, W, 3),
        "target_c2w": sds(1, T, 4, 4),
        "target_intrinsics": sds(1, T, 4),
    }
    rows.append(("stage-4 step (fwd + bwd)", train_step_model_flops(exp, _vgg19(), batch), PAPER_A100["train_step_s"]))
    a100 = PEAK_BF16_TFLOPS["A100"] * 1e12
    return [
        {
            "program": name,
            "matmul_tflop": f / 1e12,
            "h100_at_peak_s": f / H100_FLOPS,
            "paper_a100_s": paper,
            "paper_a100_peak_fraction": f / paper / a100,
        }
        for name, f, paper in rows
    ]


def markdown(result: dict) -> str:
    """The components and the programs as two Markdown tables."""
    comp = [
        (
            r["name"],
            r["shape"],
            r["per_step"],
            "bf16" if r["bf16"] else "f32 (TF32)",
            f"{r['gflops']:.4g}",
            f"{r['gbytes']:.4g}",
            f"{r['roofline_gbytes']:.4g}",
            f"{r['intensity_flops_per_byte']:.3g}",
            f"{r['h100_roofline_ms']:.4g}",
            r["bound"],
            f"{r['step_forward_ms']:.4g}",
            r["note"],
        )
        for r in result["components"]
    ]
    prog = [
        (
            r["program"],
            f"{r['matmul_tflop']:.4g}",
            f"{r['h100_at_peak_s']:.3g}",
            f"{r['paper_a100_s']:.3g}",
            f"{r['paper_a100_peak_fraction']:.1%}",
        )
        for r in result["programs"]
    ]
    return (
        markdown_table(
            (
                "component",
                "shape",
                "per step (fwd)",
                "products",
                "GFLOP",
                "GB accessed (XLA)",
                "GB (roofline)",
                "FLOP/byte",
                "H100 roofline ms",
                "bound",
                "step fwd ms",
                "note",
            ),
            comp,
        )
        + "\n\n"
        + markdown_table(
            ("program", "matmul TFLOP", "H100 at peak, s", "paper A100, s", "paper's fraction of A100 peak"), prog
        )
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=(__doc__ or "").split("\n")[0])
    ap.add_argument(
        "--out", default=os.path.join(os.path.dirname(os.path.abspath(__file__)), "results", "cost_table.json")
    )
    ap.add_argument("--only", default="", help=f"comma-separated subset of {[p.name for p in PIECES]}")
    args = ap.parse_args()
    names = [p.name for p in PIECES]
    only = [s for s in args.only.split(",") if s] or names
    unknown = sorted(set(only) - set(names))
    if unknown:
        raise SystemExit(f"--only: unknown component(s) {unknown}, expected some of {names}")
    result = {
        "config": "paper_dl3dv, stage 4 (32 + 8 views at 544x960)",
        "jax_version": jax.__version__,
        "h100": {
            "peak_bf16_flops": H100_FLOPS,
            "peak_tf32_flops": H100_TF32_FLOPS,
            "hbm_bytes_per_s": H100_BYTES_PER_S,
        },
        "components": [],
    }
    for piece in PIECES:
        if piece.name in only:
            result["components"].append(measure(piece))
            print(json.dumps(result["components"][-1]), flush=True)
    result["programs"] = programs()
    print(markdown(result))
    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    with open(args.out, "w") as f:
        json.dump(result, f, indent=1)
    print("wrote", args.out)


if __name__ == "__main__":
    main()

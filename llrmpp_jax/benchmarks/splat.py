"""Benchmark of the feature splatter: forward and forward+backward time and memory.

Sweeps N Gaussians x canvases (W x H) at F features, times ``splat.rasterize`` (jitted,
warm, best of ``--repeats``) and ``value_and_grad`` of a random linear function of its
outputs w.r.t. means, quats, scales, opacities and features, and the brute-force
``render_features_reference`` (forward; fwd+bwd too when its scan residuals fit
``--oracle-max-bytes``) where ``N x pixels <= --oracle-max-work``. Writes JSON with every
row, the oracle / splatter time ratios and the fitted exponents of time ~ N^a (per canvas)
and time ~ pixels^b (per N).

Memory: ``compiled.memory_analysis()`` (arguments + outputs + XLA temporaries, known on
every backend) and, on GPU, the allocator's peak after the runs.

Scene: one 3D scene per (N, seed) seen at every canvas size: Gaussians spread uniformly
over the frustum at depths 1-6, world scales such that their footprints are log-uniform
in [0.25, 4] pixels on a 256-pixel-wide canvas (Long-LRM++'s Gaussians are ~1 px at its
272x480 canvas) and grow with the canvas resolution, opacities uniform in [0.05, 0.5],
random rotations and features. So the work (intersections x 256 pixels) grows with N and
with the pixel count.

Primitive: ``--primitive 2dgs`` times the 2DGS splatter (``rasterize(..., primitive="2dgs")``)
on the same scene, each Gaussian's first two scales as its tangent scales, its fwd+bwd loss a
random linear function of all six outputs (features, transmittance, depth, normals, median
depth, distortion); ``both`` times the two splatters side by side. The brute-force 2DGS
reference is not timed (its distortion's pair sum is O(N^2 x pixels)).

Capacity: ``--capacity default`` uses ``SplatConfig``'s trace-time buffer (8 slots per
Gaussian), ``fitted`` sizes it from the scene as eager renders and ``refine`` do
(:func:`llrmpp_jax.splat.fit_capacity`); ``both`` (the default) times the two.

``--rounds R`` runs the sweep R times and keeps each row's median over the rounds (every
round's time under ``fwd_s_rounds`` / ``fwd_bwd_s_rounds``): a shared machine's timings drift
between runs minutes apart. A comparison with an older version of the splatter, both run on
the same machine at once, is ``experiments/bench_splat_baseline.py`` in a checkout; current
numbers and the command behind them: docs/speed-cpu.md, "The splatter".

Full sweep:                python -m llrmpp_jax.benchmarks.splat
Quick run (2-core CPU):    python -m llrmpp_jax.benchmarks.splat --quick
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
import platform
import time

import jax
import jax.numpy as jnp
import numpy as np

from llrmpp_jax.splat import SplatConfig, fit_capacity, rasterize
from llrmpp_jax.splat.reference import render_features_reference


def make_scene(rng: np.random.Generator, n: int, f: int, height: int, width: int):
    """Synthetic scene in the camera frame (c2w = identity), float32."""
    fx = fy = 0.8 * max(height, width)
    intr = np.array([fx, fy, width / 2, height / 2])
    z = rng.uniform(1.0, 6.0, n)
    u, v = rng.uniform(0, 1, n), rng.uniform(0, 1, n)  # in canvas fractions
    means = np.stack([(u - 0.5) * width / fx * z, (v - 0.5) * height / fy * z, z], -1)
    sigma_px = np.exp(rng.uniform(np.log(0.25), np.log(4.0), (n, 1)))  # at a 256-px canvas
    scales = sigma_px * z[:, None] / (0.8 * 256) * np.exp(rng.uniform(-1.0, 0.0, (n, 3)))
    quats = rng.normal(size=(n, 4))
    opac = rng.uniform(0.05, 0.5, n)
    feats = rng.normal(size=(n, f))
    return [jnp.asarray(a, jnp.float32) for a in (means, quats, scales, opac, feats, np.eye(4), intr)]


def _time(fn, args, repeats: int):
    """(compile seconds, best warm seconds, output) of ``jax.jit(fn)(*args)``."""
    t0 = time.perf_counter()
    compiled = jax.jit(fn).lower(*args).compile()
    compile_s = time.perf_counter() - t0
    out = jax.block_until_ready(compiled(*args))
    best = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(compiled(*args))
        best = min(best, time.perf_counter() - t0)
    return compile_s, best, out


def _memory(fn, args) -> dict:
    m = jax.jit(fn).lower(*args).compile().memory_analysis()
    if m is None:
        return {}
    out = {k: int(getattr(m, k)) for k in ("argument_size_in_bytes", "output_size_in_bytes", "temp_size_in_bytes")}
    out["total_bytes"] = sum(out.values())
    return out


def _device_peak() -> int | None:
    stats = jax.devices()[0].memory_stats()
    return None if not stats else int(stats.get("peak_bytes_in_use", 0))


def bench_one(
    n: int,
    width: int,
    height: int,
    f: int,
    cfg: SplatConfig,
    repeats: int,
    oracle_max_work: float,
    oracle_max_bytes: float,
    seed: int,
    fitted: bool = False,
    primitive: str = "3dgs",
) -> dict:
    rng = np.random.default_rng(seed)
    means, quats, scales, opac, feats, c2w, intr = make_scene(rng, n, f, height, width)
    if primitive == "2dgs":
        scales = scales[:, :2]
    if fitted:
        cfg = fit_capacity(means, quats, scales, opac, c2w, intr, height, width, cfg, primitive=primitive)
    planes = (
        (height, width, f),
        (height, width),
        (height, width),
        (height, width, 3),
        (height, width),
        (height, width),
    )
    cot = [jnp.asarray(rng.normal(size=s), jnp.float32) for s in planes]

    def forward(m, q, s, o, x):
        return rasterize(m, q, s, o, x, c2w, intr, height, width, cfg, primitive=primitive)

    def loss(m, q, s, o, x):
        out = forward(m, q, s, o, x)
        outs = [x for x in (*out[:3], out.normals, out.median_depth, out.distortion) if x is not None]
        return sum(jnp.sum(a * b) for a, b in zip(outs, cot))

    fwd_bwd = jax.value_and_grad(loss, argnums=(0, 1, 2, 3, 4))
    args = (means, quats, scales, opac, feats)
    fwd_compile_s, fwd_s, out = _time(forward, args, repeats)
    stats = out.stats
    row = {
        "primitive": primitive,
        "capacity_rule": "fitted" if fitted else "default",
        "n": n,
        "width": width,
        "height": height,
        "pixels": width * height,
        "features": f,
        "num_visible": int(stats.num_visible),
        "num_intersections": int(stats.num_intersections),
        "capacity": int(stats.capacity),
        "overflow": bool(stats.overflow),
        "max_tile_intersections": int(stats.max_tile_intersections),
    }
    row["fwd_compile_s"], row["fwd_s"] = fwd_compile_s, fwd_s
    row["fwd_memory"] = _memory(forward, args)
    row["fwd_bwd_compile_s"], row["fwd_bwd_s"], _ = _time(fwd_bwd, args, repeats)
    row["fwd_bwd_memory"] = _memory(fwd_bwd, args)
    row["device_peak_bytes"] = _device_peak()

    if primitive == "3dgs" and n * width * height <= oracle_max_work:

        def oracle(m, q, s, o, x):
            return render_features_reference(m, q, s, o, x, c2w, intr, height, width, cfg)

        _, row["oracle_fwd_s"], _ = _time(oracle, args, max(1, repeats // 2))
        row["oracle_fwd_ratio"] = row["oracle_fwd_s"] / row["fwd_s"]
        residual_bytes = 4.0 * n * width * height * (f + 3)  # the scan carries per step
        if residual_bytes <= oracle_max_bytes:

            def oracle_loss(m, q, s, o, x):
                return sum(jnp.sum(a * b) for a, b in zip(oracle(m, q, s, o, x), cot))

            _, row["oracle_fwd_bwd_s"], _ = _time(jax.value_and_grad(oracle_loss, argnums=(0, 1, 2, 3, 4)), args, 1)
            row["oracle_fwd_bwd_ratio"] = row["oracle_fwd_bwd_s"] / row["fwd_bwd_s"]
    return row


def fit_exponents(rows: list[dict], key: str) -> dict:
    """Slopes of log(time) against log(N) per canvas and against log(pixels) per N."""
    fits: dict = {"vs_n": {}, "vs_pixels": {}}
    canvases = sorted({(r["width"], r["height"]) for r in rows})
    for w, h in canvases:
        pts = [(r["n"], r[key]) for r in rows if (r["width"], r["height"]) == (w, h)]
        if len(pts) >= 2:
            x, y = np.log([p[0] for p in pts]), np.log([p[1] for p in pts])
            fits["vs_n"][f"{w}x{h}"] = float(np.polyfit(x, y, 1)[0])
    for n in sorted({r["n"] for r in rows}):
        pts = [(r["pixels"], r[key]) for r in rows if r["n"] == n]
        if len(pts) >= 2:
            x, y = np.log([p[0] for p in pts]), np.log([p[1] for p in pts])
            fits["vs_pixels"][str(n)] = float(np.polyfit(x, y, 1)[0])
    return fits


def median_rows(runs: list[list[dict]]) -> list[dict]:
    """Rows of repeated sweeps merged: each timing key the median over the runs (every
    run's value under ``KEY_rounds``), the rest from the first run."""
    out = []
    for rows in zip(*runs, strict=True):
        row = dict(rows[0])
        for key in ("fwd_s", "fwd_bwd_s"):
            values = [r[key] for r in rows]
            row[key], row[f"{key}_rounds"] = float(np.median(values)), values
        out.append(row)
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--n", type=float, nargs="+", default=[1e4, 1e5, 1e6], help="numbers of Gaussians")
    parser.add_argument("--canvas", nargs="+", default=["128x128", "256x256", "480x272"], help="WxH canvases")
    parser.add_argument("--features", type=int, default=32, help="feature width F")
    parser.add_argument("--repeats", type=int, default=3, help="timed runs after the compile (best is kept)")
    parser.add_argument("--chunk-size", type=int, default=SplatConfig.chunk_size, help="SplatConfig.chunk_size")
    parser.add_argument(
        "--tiles-per-group", type=int, default=SplatConfig.tiles_per_group, help="SplatConfig.tiles_per_group"
    )
    parser.add_argument(
        "--composite-tile",
        type=int,
        default=SplatConfig.composite_tile,
        help="SplatConfig.composite_tile (pixels a side of a compositor block)",
    )
    parser.add_argument(
        "--capacity",
        choices=("default", "fitted", "both"),
        default="both",
        help="intersection buffer: SplatConfig's default, fitted to the scene, or both",
    )
    parser.add_argument("--primitive", choices=("3dgs", "2dgs", "both"), default="3dgs", help="splatter(s) to time")
    parser.add_argument("--oracle-max-work", type=float, default=2e8, help="largest N x pixels for the oracle")
    parser.add_argument("--oracle-max-bytes", type=float, default=2e9, help="largest oracle fwd+bwd residuals")
    parser.add_argument("--quick", action="store_true", help="N in {1e4, 1e5}, canvases 128x128 and 256x256")
    parser.add_argument("--seed", type=int, default=0, help="scene seed")
    parser.add_argument("--rounds", type=int, default=1, help="sweeps; each row keeps its median time")
    parser.add_argument("--out", default=os.path.join("runs", "bench", "bench_splat.json"), help="JSON file to write")
    args = parser.parse_args()
    if args.quick:
        args.n, args.canvas = [1e4, 1e5], ["128x128", "256x256"]
    if args.rounds < 1:
        parser.error(f"--rounds must be >= 1, got {args.rounds}")

    cfg = SplatConfig(
        chunk_size=args.chunk_size, tiles_per_group=args.tiles_per_group, composite_tile=args.composite_tile
    )
    rules = {"default": [False], "fitted": [True], "both": [False, True]}[args.capacity]
    primitives = ["3dgs", "2dgs"] if args.primitive == "both" else [args.primitive]

    def sweep() -> list[dict]:
        rows = []
        for canvas in args.canvas:
            width, height = (int(v) for v in canvas.lower().split("x"))
            for n, fitted, primitive in itertools.product(args.n, rules, primitives):
                row = bench_one(
                    int(n),
                    width,
                    height,
                    args.features,
                    cfg,
                    args.repeats,
                    args.oracle_max_work,
                    args.oracle_max_bytes,
                    args.seed,
                    fitted,
                    primitive,
                )
                rows.append(row)
                print(json.dumps({k: v for k, v in row.items() if not isinstance(v, dict)}), flush=True)
        return rows

    rows = median_rows([sweep() for _ in range(args.rounds)])

    exponents_by = {
        p: {key: fit_exponents([r for r in rows if r["primitive"] == p], key) for key in ("fwd_s", "fwd_bwd_s")}
        for p in primitives
    }
    exponents = exponents_by[primitives[0]]
    result = {
        "device": str(jax.devices()[0]),
        "backend": jax.default_backend(),
        "jax": jax.__version__,
        "host": platform.node(),
        "cpu_count": os.cpu_count(),
        "config": vars(args) | {"splat": repr(cfg)},
        "rows": rows,
        "exponents": exponents if len(primitives) == 1 else {"by_primitive": exponents_by},
    }
    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    with open(args.out, "w") as fh:
        json.dump(result, fh, indent=1)
    print(json.dumps(result["exponents"], indent=1))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()

"""Benchmark of the viewer's render latency: one frame of ``llrmpp view`` per camera.

The demo's tiny model (random init; timing does not depend on the weights) reconstructs a
procedural scene, then :class:`~llrmpp_jax.viewer.render.ViewRenderer` renders it at
square canvases of 128 and 256 pixels: RGB through splat + decoder with S=2 and S=1
partition copies, and depth (the demo model has no depth head: splatted depth). For each:
compile seconds (once per size, what the page's "compiling" notice covers) and the warm
per-frame time (device-synced, median and min of ``--repeats`` renders at cameras along
the inputs), plus the frame's conversion to display pixels. Writes JSON.

Run:  python experiments/bench_viewer.py            (-> experiments/results/bench_viewer.json)
      python experiments/bench_viewer.py --checkpoint pretrained:small --inputs 8 \
          --out experiments/results/bench_viewer_small.json      (the shipped small model)
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time

import jax
import numpy as np

from llrmpp_jax.experiment import load_experiment
from llrmpp_jax.model import init_params
from llrmpp_jax.params_io import load_params
from llrmpp_jax.viewer.render import ViewKey, ViewRenderer, display_image, viewport_camera
from llrmpp_jax.viewer.scene import procedural_view_scene

HERE = os.path.dirname(os.path.abspath(__file__))


def main() -> None:
    ap = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    ap.add_argument("--sizes", default="128,256", help="square render sizes (px)")
    ap.add_argument("--inputs", type=int, default=4, help="input views of the procedural scene")
    ap.add_argument("--input-size", type=int, default=64, help="input view size (px)")
    ap.add_argument("--repeats", type=int, default=10, help="timed renders per (size, output, S)")
    ap.add_argument(
        "--checkpoint",
        default=None,
        help="a trained model (workdir, params folder or pretrained:NAME); default: the demo's "
        "tiny model at random init (timing does not depend on the weights)",
    )
    ap.add_argument("--out", default=os.path.join(HERE, "results", "bench_viewer.json"), help="JSON report path")
    args = ap.parse_args()

    if args.checkpoint:
        params, cfg = load_params(args.checkpoint)
    else:
        cfg = load_experiment("demo").model
        params = init_params(jax.random.key(0), cfg, 1, cfg.size_multiple, cfg.size_multiple)
    m = cfg.size_multiple
    scene = procedural_view_scene(params, cfg, seed=0, num_inputs=args.inputs, size=args.input_size)
    renderer = ViewRenderer(params, cfg, scene.gaussians)
    fov = float(2.0 * np.arctan(scene.input_hw[0] / (2.0 * scene.input_intrinsics[0, 1])))
    rows = []
    for size in (int(s) for s in args.sizes.split(",")):
        h, w, k = viewport_camera(fov, 1.0, size, m)
        for output, s in (("rgb", cfg.decoder.partitions), ("rgb", 1), ("depth", cfg.decoder.partitions)):
            key = ViewKey(h, w, output, s)
            compile_s = renderer.compile(key)
            renderer.render(key, scene.input_c2w[0], k)  # first run (allocation) not counted
            times, display = [], []
            for i in range(args.repeats):
                frame = renderer.render(key, scene.input_c2w[i % len(scene.input_c2w)], k)
                t0 = time.perf_counter()
                display_image(frame.image, output)
                display.append(time.perf_counter() - t0)
                times.append(frame.render_s)
            row = {
                "height": h,
                "width": w,
                "output": output,
                "partitions": s,
                "compile_s": compile_s,
                "render_ms_median": 1e3 * float(np.median(times)),
                "render_ms_min": 1e3 * float(np.min(times)),
                "display_ms_median": 1e3 * float(np.median(display)),
            }
            rows.append(row)
            print(json.dumps(row), flush=True)
    report = {
        "what": "per-frame render latency of the viewer (ViewRenderer.render, device-synced)",
        "model": args.checkpoint or "demo recipe model (config.tiny with the demo head), random init",
        "scene": f"procedural seed 0, {args.inputs} inputs at {args.input_size}x{args.input_size}",
        "num_gaussians": int(scene.gaussians.means.shape[1]),
        "repeats": args.repeats,
        "device": str(jax.devices()[0]),
        "cpu_count": os.cpu_count(),
        "machine": platform.machine(),
        "load_average_at_end": os.getloadavg(),
        "rows": rows,
    }
    os.makedirs(os.path.dirname(args.out), exist_ok=True)
    with open(args.out, "w") as f:
        json.dump(report, f, indent=1)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()

"""Data-pipeline throughput on this machine, written as JSON.

* procedural scenes per second: a fresh seed's layout + ray casting of ``views`` frames
  (RGB + depth), and a full training sample (8 inputs + 4 targets, selection, cropping,
  normalisation) through :func:`llrmpp_jax.data.batching.build_sample`;
* real-capture frames per second: decode + undistort + resize + square crop of the
  fox (1080x1920 JPEG, OpenCV distortion) and beer (720x1280 JPEG, COLMAP SIMPLE_RADIAL)
  frames from ``../shared/data``.

Each figure is single-threaded (one worker); the batch iterator runs ``num_workers`` of
these in parallel. Usage: ``python experiments/bench_data.py [--out PATH] [--repeats N]``.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time
import warnings

import numpy as np

from llrmpp_jax.data.batching import BatchConfig, ProceduralSource, build_sample
from llrmpp_jax.data.formats import read_colmap_scene, read_nerfstudio_scene
from llrmpp_jax.data.preprocess import ViewGeometry, crop_box, load_views, output_size, resized_size
from llrmpp_jax.data.synthetic import ProceduralConfig, procedural_layout, render_views
from llrmpp_jax.data.textures import texture_bank

SHARED = os.path.abspath(os.path.join(os.path.dirname(__file__), "..", "..", "shared", "data"))


def _rate(fn, count: int, repeats: int) -> dict[str, float]:
    """Run ``fn(r)`` for r in 1..repeats after one warm-up (r = 0); ``count`` items per call."""
    fn(0)
    times = []
    for r in range(1, repeats + 1):
        t0 = time.perf_counter()
        fn(r)
        times.append(time.perf_counter() - t0)
    return {"per_second": count / float(np.median(times)), "median_s": float(np.median(times)), "repeats": repeats}


def bench_procedural(size: int, views: int, repeats: int) -> dict[str, dict[str, float]]:
    cfg = ProceduralConfig(height=size, width=size, num_frames=views)

    def render(r: int) -> None:
        lay, c2w, k, _ = procedural_layout(1000 + r, cfg)
        render_views(lay, c2w, k, size, size)

    src = ProceduralSource(ProceduralConfig(height=size, width=size, num_frames=32))
    bcfg = BatchConfig(global_batch=1, num_inputs=8, num_targets=4, with_depth=True)

    def sample(r: int) -> None:
        build_sample(src, bcfg, np.random.default_rng([7, r]))

    return {
        f"scene_{views}_views": _rate(render, 1, repeats),
        "training_sample_8in_4tg": _rate(sample, 1, repeats),
    }


def bench_capture(scene, size: int, frames: int, repeats: int) -> dict[str, float]:
    geom = ViewGeometry(
        resize_w=size if scene.hw[0, 0] > scene.hw[0, 1] else None,
        resize_h=size if scene.hw[0, 0] <= scene.hw[0, 1] else None,
        square_crop=True,
    )
    hw = tuple(scene.hw[0])
    resized, out_hw = resized_size(hw, geom), output_size(hw, geom)
    box = crop_box(resized, geom)

    def load(r: int) -> None:
        start = (r + 1) * frames % max(1, len(scene) - frames)
        load_views(scene, np.arange(start, start + frames), resized, box, None, False)

    out = _rate(load, frames, repeats)
    out["output_hw"] = list(out_hw)  # pyright: ignore[reportArgumentType] -- a JSON row: mixed values
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=(__doc__ or "").split("\n")[0])
    parser.add_argument("--out", default=os.path.join(os.path.dirname(__file__), "results", "bench_data.json"))
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()
    t0 = time.perf_counter()
    texture_bank()
    result: dict = {
        "machine": {"cpus": os.cpu_count(), "platform": platform.platform(), "load_average": os.getloadavg()},
        "texture_bank_load_s": time.perf_counter() - t0,
        "procedural": {str(s): bench_procedural(s, 8, args.repeats) for s in (128, 256)},
        "capture": {},
    }
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the fox's 17 missing images
        captures = {
            "fox_nerfstudio_1080x1920_distorted": read_nerfstudio_scene(os.path.join(SHARED, "fox")),
            "beer_colmap_720x1280_simple_radial": read_colmap_scene(
                os.path.join(SHARED, "beer", "sparse", "0"), os.path.join(SHARED, "beer", "images")
            ),
        }
    for name, scene in captures.items():
        result["capture"][name] = {str(s): bench_capture(scene, s, 4, args.repeats) for s in (128, 256)}
    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    with open(args.out, "w") as f:
        json.dump(result, f, indent=2)
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()

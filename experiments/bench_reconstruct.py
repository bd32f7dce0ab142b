"""Reconstruction time of ``llrmpp reconstruct`` on the two sample captures.

Run:  PYTHONPATH=. python experiments/bench_reconstruct.py [--sizes 64 128] [--inputs 8] [--repeats 5]

For fox (nerfstudio) and beer (COLMAP) in ../shared/data, with the golden tiny Long-LRM
converted from ../shared/golden/long_lrm_tiny/state_dict.npz (colour mode): k-means inputs,
views of height ``size`` keeping the aspect ratio, :func:`llrmpp_jax.capture.reconstruct_scene`.
Compile time is measured apart (``jit(...).lower().compile()``); the run time is the median
of ``--repeats`` runs, each synced with ``block_until_ready``. Writes
experiments/results/bench_reconstruct.json.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import warnings

import jax
import numpy as np

from llrmpp_jax.capture import reconstruct_scene, select_views
from llrmpp_jax.convert.long_lrm import convert_long_lrm
from llrmpp_jax.convert.table import load_torch_state_dict
from llrmpp_jax.data.formats import read_scene

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
SHARED = os.path.join(ROOT, "..", "shared")
RESULTS = os.path.join(ROOT, "experiments", "results", "bench_reconstruct.json")


def main() -> None:
    ap = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[64, 128], help="view heights")
    ap.add_argument("--inputs", type=int, default=8, help="input views")
    ap.add_argument("--repeats", type=int, default=5, help="timed runs per setting (median reported)")
    args = ap.parse_args()
    sys.path.insert(0, ROOT)
    from tests.helpers.golden import golden_model_config

    cfg = golden_model_config()
    params = convert_long_lrm(
        load_torch_state_dict(os.path.join(SHARED, "golden", "long_lrm_tiny", "state_dict.npz")), cfg
    )
    rows = []
    for name in ("fox", "beer"):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # fox lists 17 frames without a photo
            scene = read_scene(os.path.join(SHARED, "data", name))
        inputs, targets = select_views(scene, args.inputs)
        for size in args.sizes:
            rec = reconstruct_scene(params, cfg, scene, inputs, targets, (size, None), repeats=args.repeats)
            row = {
                "scene": name,
                "view_hw": list(rec.saved.image_hw),
                "num_inputs": args.inputs,
                "gaussians": int(rec.saved.gaussians.means.shape[0]),
                "compile_s": rec.compile_s,
                "run_s_median": rec.run_s,
                "runs_s": list(rec.runs_s),
            }
            rows.append(row)
            print(json.dumps(row))
    out = {
        "device": str(jax.devices()[0]),
        "cpu_count": os.cpu_count(),
        "model": "golden tiny Long-LRM (colour)",
        "note": "shared 2-core CPU box, other jobs running; run = median of synced runs; "
        "beer reuses fox's compiled executables (same shapes), so its compile_s is a cache hit",
        "rows": rows,
        "median_run_s_overall": float(np.median([r["run_s_median"] for r in rows])),
    }
    os.makedirs(os.path.dirname(RESULTS), exist_ok=True)
    with open(RESULTS, "w") as f:
        json.dump(out, f, indent=1)


if __name__ == "__main__":
    main()

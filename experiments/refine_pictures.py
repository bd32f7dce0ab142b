"""Pictures of the shipped model's novel views before and after post-prediction refinement.

Run:  python experiments/refine_pictures.py --steps 10 --scenes 3 --out experiments/results/small/refined_10.png
      python experiments/refine_pictures.py --steps 10 --data ../shared/data/beer --size 112x64 --out beer.png

For the first ``--scenes`` held-out scenes of the ``small`` recipe (or of the captures at
``--data``, split as ``llrmpp eval --data`` splits them: k-means inputs, every 8th frame a
target; ``--size`` as ``eval --size``, before the config's square crop), one row per target
view: the target, the model's prediction, the prediction after its Gaussians were refined
``--steps`` steps against the scene's 8 inputs (``evaluate.predict_refined``, the row
``refined_N`` of ``llrmpp eval --refine-steps N``), and the nearest input view. Scaled up
``--zoom`` times (nearest neighbour) so the 64x64 views can be read.
"""

from __future__ import annotations

import argparse
from dataclasses import replace

import numpy as np

from llrmpp_jax.cli import parse_size, with_data
from llrmpp_jax.data.image_io import write_image
from llrmpp_jax.evaluate import baseline_predictions, predict, predict_refined
from llrmpp_jax.experiment import load_experiment
from llrmpp_jax.experiment_data import eval_samples
from llrmpp_jax.pretrained import load_pretrained


def main() -> None:
    ap = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    ap.add_argument("--steps", type=int, default=100, help="refinement steps per scene")
    ap.add_argument("--scenes", type=int, default=4, help="how many held-out scenes (from the first)")
    ap.add_argument("--zoom", type=int, default=3, help="nearest-neighbour upscaling of the picture")
    ap.add_argument("--data", default=None, help="capture folder or dataset root instead of the procedural scenes")
    ap.add_argument("--size", default=None, help="with --data: view size H or HxW before the square crop")
    ap.add_argument("--out", required=True, help="PNG to write")
    args = ap.parse_args()
    exp = load_experiment("small")
    if args.data:
        exp = with_data(exp, args.data, "auto", args.scenes)
        if args.size:
            resize_h, resize_w = parse_size(args.size)
            exp = replace(exp, stages=(*exp.stages[:-1], replace(exp.stages[-1], resize_h=resize_h, resize_w=resize_w)))
    params, cfg = load_pretrained("small", exp.model)
    samples, names = eval_samples(exp, exp.stages[-1])
    rows = []
    for s, name in zip(samples[: args.scenes], names, strict=False):
        batch = {k: v[None] for k, v in s.items()}
        model = np.asarray(predict(params, cfg, batch)["rgb"][0])
        refined = np.asarray(predict_refined(params, cfg, batch, args.steps)["rgb"][0])
        nearest = baseline_predictions(s)["nearest_view"]
        for t in range(s["target_images"].shape[0]):
            views = [s["target_images"][t], model[t], refined[t], nearest[t]]
            rows.append(
                np.concatenate(
                    [np.pad(np.clip(v, 0, 1), ((1, 1), (1, 1), (0, 0)), constant_values=1.0) for v in views], axis=1
                )
            )
        print(f"{name}: done")
    picture = np.concatenate(rows, axis=0).repeat(args.zoom, axis=0).repeat(args.zoom, axis=1)
    write_image(args.out, picture)
    print(f"wrote {args.out}: per row target | model | refined {args.steps} steps | nearest input view")


if __name__ == "__main__":
    main()

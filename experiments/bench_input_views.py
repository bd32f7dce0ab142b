"""What a model's input-view re-render is made of: all views' Gaussians, the view's own, or one view alone.

Run:  PYTHONPATH=. python experiments/bench_input_views.py --checkpoint pretrained:small
      PYTHONPATH=. python experiments/bench_input_views.py --checkpoint ~/runs/small --config small --name small_6000

On the experiment's held-out procedural scenes (``--config``, default the checkpoint's own
``small.py``), each input view is re-rendered three ways and scored (PSNR against the input):

* ``all_views``: from every input view's Gaussians (what ``evaluate``'s ``input_psnr`` reports);
* ``own_only``: from the same reconstruction with every other view's Gaussians made
  transparent (opacity 0), so nothing of the other views can cover it;
* ``single_input``: reconstructed from that view alone.

and, for scale, the image's own 8 x 8, 4 x 4 and 2 x 2 block means. If ``all_views`` is far
below ``own_only``, other views' Gaussians (at wrong depths) spoil the view; if ``own_only`` is
at the 8 x 8 block mean, the model passes each patch's mean colour and nothing finer. Writes
``experiments/results/learning/input_views_<name>.json``.
"""

from __future__ import annotations

import argparse
import json
import os

import jax
import jax.numpy as jnp
import numpy as np

from llrmpp_jax.experiment import load_experiment
from llrmpp_jax.experiment_data import eval_samples
from llrmpp_jax.metrics import psnr
from llrmpp_jax.model import reconstruct, render
from llrmpp_jax.params_io import load_params

RESULTS = os.path.join(os.path.dirname(os.path.abspath(__file__)), "results", "learning")


def block_mean(images: np.ndarray, b: int) -> np.ndarray:
    """``[V, H, W, 3]`` -> each ``b x b`` block replaced by its mean colour."""
    v, h, w, c = images.shape
    m = images.reshape(v, h // b, b, w // b, b, c).mean(axis=(2, 4), keepdims=True)
    return np.broadcast_to(m, (v, h // b, b, w // b, b, c)).reshape(images.shape)


def score(a, b) -> float:
    return float(jnp.mean(psnr(jnp.clip(jnp.asarray(a), 0.0, 1.0), jnp.asarray(b))))


def main() -> None:
    p = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    p.add_argument(
        "--checkpoint", default="pretrained:small", help="training workdir, params folder or pretrained:NAME"
    )
    p.add_argument("--config", default="small", help="experiment file whose held-out scenes and view counts are used")
    p.add_argument("--name", default=None, help="result name (default: the checkpoint's last path part)")
    args = p.parse_args()
    exp = load_experiment(args.config)
    params, cfg = load_params(os.path.expanduser(args.checkpoint), exp.model)
    stage = exp.stages[-1]
    samples, names = eval_samples(exp, stage)
    v = stage.num_inputs

    rec = jax.jit(lambda im, c2w, k: reconstruct(params, cfg, im, c2w, k))
    ren = jax.jit(lambda g, c2w, k, h, w: render(params, cfg, g, c2w, k, h, w).images["rgb"], static_argnums=(3, 4))
    rows = []
    for name, s in zip(names, samples):
        im, c2w, k = (jnp.asarray(s[x])[None] for x in ("input_images", "input_c2w", "input_intrinsics"))
        h, w = s["input_images"].shape[1:3]
        g = rec(im, c2w, k)
        per_view = g.means.shape[1] // v
        own, single = [], []
        for i in range(v):
            mask = (jnp.arange(v * per_view) // per_view == i).astype(g.opacities.dtype)[None]
            cam = (c2w[:, i : i + 1], k[:, i : i + 1])
            own.append(score(ren(g._replace(opacities=g.opacities * mask), *cam, h, w)[0, 0], s["input_images"][i]))
            alone = rec(im[:, i : i + 1], *cam)
            single.append(score(ren(alone, *cam, h, w)[0, 0], s["input_images"][i]))
        blocks = {f"block_mean_{b}": score(block_mean(s["input_images"], b), s["input_images"]) for b in (8, 4, 2)}
        rows.append(
            {
                "scene": name,
                "all_views": score(ren(g, c2w, k, h, w)[0], s["input_images"]),
                "own_only": float(np.mean(own)),
                "single_input": float(np.mean(single)),
                **blocks,
            }
        )
        print(" ".join(f"{k_}={v_:.2f}" if isinstance(v_, float) else v_ for k_, v_ in rows[-1].items()), flush=True)
    mean = {k_: float(np.mean([r[k_] for r in rows])) for k_ in rows[0] if k_ != "scene"}
    print("mean over scenes (PSNR dB): " + ", ".join(f"{k_} {v_:.2f}" for k_, v_ in mean.items()))
    name = args.name or os.path.basename(os.path.normpath(args.checkpoint)).replace("pretrained:", "pretrained_")
    os.makedirs(RESULTS, exist_ok=True)
    with open(os.path.join(RESULTS, f"input_views_{name}.json"), "w") as f:
        json.dump(
            {"checkpoint": args.checkpoint, "config": os.path.relpath(args.config), "mean": mean, "scenes": rows},
            f,
            indent=1,
        )


if __name__ == "__main__":
    main()

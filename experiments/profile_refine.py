"""Profile of one refinement step and of the splatter on this machine, per phase.

Run (the committed table, docs/results.md "Refinement"; a 32-input reconstruction of the
beer capture at 256x192 by the shipped model, then the splatter alone at 100k Gaussians):

  llrmpp reconstruct --checkpoint pretrained:small --scene ../shared/data/beer --num-inputs 32 \\
      --size 256x192 --out ~/runs/beer32.gs
  python experiments/profile_refine.py --gaussians ~/runs/beer32.gs --checkpoint pretrained:small \\
      --out experiments/results/profile_refine.json

Each program is compiled once (timed: "compile"), run, then profiled over ``--repeats``
calls with ``jax.profiler`` (:func:`llrmpp_jax.profiling.profile_program`): milliseconds
per call per phase (projection, binning, sort, composite forward and backward, decoder,
loss, ...) and the top ops. Programs: the refinement objective's value and gradient on
``--views-per-step`` input views (what one update computes; Adam's update is negligible),
and the splatter's (``splat.rasterize``, rows labelled ``render_features``) forward and
forward+backward on ``llrmpp_jax.benchmarks.splat``'s scene (100k Gaussians, 128x128, F=32).
Writes JSON and prints a Markdown table.
"""

from __future__ import annotations

import argparse
import json
import os
import platform

import jax
import jax.numpy as jnp
import numpy as np

from llrmpp_jax.profiling import profile_program


def refine_step_profile(args) -> dict:
    from llrmpp_jax.capture import load_gs
    from llrmpp_jax.capture.render import frame_photos
    from llrmpp_jax.gaussians import Gaussians
    from llrmpp_jax.model import fit_capacity
    from llrmpp_jax.params_io import load_params
    from llrmpp_jax.refine import RefineConfig, objective, to_unconstrained

    saved = load_gs(args.gaussians)
    params, _ = load_params(args.checkpoint, saved.model)
    idx = saved.inputs[: args.views_per_step]
    images = jnp.asarray(frame_photos(saved, idx, args.scene)[None])
    c2w = jnp.asarray(saved.c2w[idx][None], jnp.float32)
    intr = jnp.asarray(saved.intrinsics[idx][None], jnp.float32)
    g = Gaussians(*(jnp.asarray(x)[None] for x in saved.gaussians))
    h, w = images.shape[2:4]
    rc = RefineConfig(views_per_step=args.views_per_step)
    cfg = fit_capacity(params, saved.model, g, c2w, intr, h, w, headroom=rc.capacity_headroom)
    fn = objective(cfg, rc)
    grad = jax.value_and_grad(fn, has_aux=True)
    prof = profile_program(
        lambda y, a: grad(y, a), (to_unconstrained(g, cfg), (params, images, c2w, intr, None)), repeats=args.repeats
    )
    return {
        "program": "refine objective value+grad",
        "gaussians": int(g.means.shape[1]),
        "views": args.views_per_step,
        "view_hw": [int(h), int(w)],
        "capacity": int(cfg.splat.max_intersections),  # pyright: ignore[reportArgumentType] -- refine's config sets the capacity
    } | prof.to_json()


def splat_profiles(args) -> list[dict]:
    from llrmpp_jax.benchmarks.splat import make_scene
    from llrmpp_jax.splat import SplatConfig, rasterize

    n, (wd, ht) = 100_000, (128, 128)
    means, quats, scales, opac, feats, c2w, intr = make_scene(np.random.default_rng(0), n, 32, ht, wd)
    cfg = SplatConfig()
    cot = jnp.asarray(np.random.default_rng(1).normal(size=(ht, wd, 32)), jnp.float32)

    def forward(m, q, s, o, x):
        return rasterize(m, q, s, o, x, c2w, intr, ht, wd, cfg)[:3]

    def loss(m, q, s, o, x):
        f, t, d = forward(m, q, s, o, x)
        return jnp.sum(f * cot) + jnp.sum(t) + jnp.sum(d)

    arrays = (means, quats, scales, opac, feats)
    out = []
    for name, fn in (
        ("render_features forward", forward),
        ("render_features forward+backward", jax.value_and_grad(loss, argnums=(0, 1, 2, 3, 4))),
    ):
        prof = profile_program(fn, arrays, repeats=args.repeats)
        out.append({"program": name, "gaussians": n, "canvas": f"{wd}x{ht}", "features": 32} | prof.to_json())
    return out


def markdown(programs: list[dict]) -> str:
    lines = []
    for p in programs:
        lines.append(
            f"**{p['program']}** ({p.get('gaussians')} Gaussians): compile {p['compile_s']:.1f} s, "
            f"run {p['wall_ms']:.0f} ms"
        )
        lines.append("")
        lines.append("| phase | ms per call |")
        lines.append("|---|---|")
        lines += [f"| {k} | {v:.1f} |" for k, v in p["phases_ms"].items()]
        lines.append("")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--gaussians", help="a .gs file from llrmpp reconstruct (omit: the splatter alone)")
    parser.add_argument("--checkpoint", default="pretrained:small", help="the model that made the .gs file")
    parser.add_argument("--scene", default=None, help="the capture (default: the path in the .gs file)")
    parser.add_argument("--views-per-step", type=int, default=8, help="input views in the profiled update")
    parser.add_argument("--repeats", type=int, default=3, help="profiled calls per program")
    parser.add_argument("--out", default="experiments/results/profile_refine.json", help="JSON file to write")
    args = parser.parse_args()
    programs = ([refine_step_profile(args)] if args.gaussians else []) + splat_profiles(args)
    result = {
        "device": str(jax.devices()[0]),
        "backend": jax.default_backend(),
        "jax": jax.__version__,
        "host": platform.node(),
        "cpu_count": os.cpu_count(),
        "config": {k: v for k, v in vars(args).items()},
        "programs": programs,
    }
    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    with open(args.out, "w") as fh:
        json.dump(result, fh, indent=1)
    print(markdown(programs))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()

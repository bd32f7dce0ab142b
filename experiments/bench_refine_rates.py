"""Post-prediction refinement's learning rates and loss, chosen on validation scenes.

Run:  python experiments/bench_refine_rates.py --checkpoint pretrained:small --scenes 8 --steps 10 \
          --variants 1:0 3:0 10:0 3:0.5
      python experiments/bench_refine_rates.py --steps 10 --name small_10_fields \
          --variants 10:0 10:0:means=3 10:0:means=0.3 10:0:features=3,opacity_logits=0.3

``refine.RefineConfig``'s per-field rates were picked by hand. Each variant
``SCALE:PERCEPTUAL`` sets its ``rate_scale`` (every rate times ``SCALE``; the default,
:func:`llrmpp_jax.refine.rate_scale_for` the steps, was chosen from these runs) and its
perceptual weight (0: MSE only, the default; the paper trains with 0.5); an optional third
part ``FIELD=FACTOR,...`` multiplies single fields' rates on top (``FIELD`` one of
``means log_scales quats opacity_logits features``: ``RefineConfig.lr_FIELD``), then
``evaluate(..., refine_steps=--steps)`` scores the refined Gaussians on held-out targets.
The scenes are *validation* scenes: procedural seeds ``--seed-offset`` above the held-out
evaluation's (``DataConfig.eval_seed_offset``), so neither the 16 held-out scenes the README
reports nor any training scene is used to choose. Writes
``experiments/results/refine_rates/<name>.json``: per variant the refined row (PSNR, SSIM,
LPIPS, input-view fit), the unrefined model's row once, and the wall time; rewritten after
every variant, so a stopped run keeps what it measured.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import time
from dataclasses import replace

from llrmpp_jax.evaluate import evaluate
from llrmpp_jax.experiment import load_experiment
from llrmpp_jax.experiment_data import eval_samples
from llrmpp_jax.metrics import load_lpips_params
from llrmpp_jax.params_io import load_params
from llrmpp_jax.refine import RefineConfig

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
# The fields with a rate of their own: RefineConfig's lr_FIELD.
FIELDS = tuple(f.name.removeprefix("lr_") for f in dataclasses.fields(RefineConfig) if f.name.startswith("lr_"))


def parse_variant(text: str) -> tuple[float, float, dict[str, float]]:
    """``"SCALE:PERCEPTUAL[:FIELD=FACTOR,...]"`` -> ``(scale, perceptual, {field: factor})``;
    argparse's error on anything else."""
    parts = text.split(":")
    try:
        if len(parts) not in (2, 3):
            raise ValueError
        scale, perceptual = float(parts[0]), float(parts[1])
        fields = {}
        for item in parts[2].split(",") if len(parts) == 3 else []:
            field, factor = item.split("=")
            fields[field] = float(factor)
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"a variant is SCALE:PERCEPTUAL[:FIELD=FACTOR,...] (e.g. 3:0.5 or 10:0:means=3), got {text!r}"
        ) from None
    unknown = sorted(set(fields) - set(FIELDS))
    if unknown:
        raise argparse.ArgumentTypeError(f"variant {text!r}: unknown field {unknown[0]!r}; expected one of {FIELDS}")
    if scale <= 0 or perceptual < 0 or any(v <= 0 for v in fields.values()):
        raise argparse.ArgumentTypeError(f"a variant needs SCALE > 0, PERCEPTUAL >= 0, FACTOR > 0, got {text!r}")
    return scale, perceptual, fields


def main() -> None:
    p = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    p.add_argument(
        "--config",
        default="small",
        help="recipe or experiment file: its procedural data and last stage's views (default: small)",
    )
    p.add_argument(
        "--checkpoint", default="pretrained:small", help="training workdir, params folder or pretrained:NAME"
    )
    p.add_argument("--scenes", type=int, default=8, help="validation scenes")
    p.add_argument(
        "--seed-offset", type=int, default=1_000, help="validation seeds start this far above the held-out evaluation's"
    )
    p.add_argument("--steps", type=int, default=10, help="refinement steps (the paper's Table 1: 10)")
    p.add_argument(
        "--variants",
        type=parse_variant,
        nargs="+",
        default=[(1.0, 0.0, {}), (3.0, 0.0, {}), (10.0, 0.0, {})],
        help="SCALE:PERCEPTUAL[:FIELD=FACTOR,...]: all learning rates times SCALE, perceptual weight, "
        "single fields' rates times FACTOR on top",
    )
    p.add_argument("--name", default="small_10", help="results file name (experiments/results/refine_rates/NAME.json)")
    args = p.parse_args()

    exp = load_experiment(args.config)
    if exp.data.kind != "procedural":
        p.error(f"--config {args.config}: validation scenes are procedural seeds, its data is {exp.data.kind!r}")
    params, cfg = load_params(args.checkpoint, exp.model)
    data = replace(exp.data, num_eval_scenes=args.scenes, eval_seed_offset=exp.data.eval_seed_offset + args.seed_offset)
    exp = replace(exp, data=data, model=cfg)
    samples, names = eval_samples(exp, exp.stages[-1])
    lpips_params = load_lpips_params()  # its VGG16 is also the refinement's perceptual network
    path = os.path.join(ROOT, "experiments", "results", "refine_rates", f"{args.name}.json")
    os.makedirs(os.path.dirname(path), exist_ok=True)
    defaults = RefineConfig()
    out = {
        "checkpoint": args.checkpoint,
        "config": os.path.relpath(args.config, ROOT),
        "scenes": names,
        "steps": args.steps,
        "defaults": dataclasses.asdict(defaults),
        "variants": [],
    }
    for scale, perceptual, fields in args.variants:
        rc = dataclasses.replace(
            defaults,
            rate_scale=scale,
            perceptual_weight=perceptual,
            **{f"lr_{k}": getattr(defaults, f"lr_{k}") * v for k, v in fields.items()},
        )
        t0 = time.perf_counter()
        _, summary, _ = evaluate(
            params, cfg, samples, lpips_params, names, refine_steps=args.steps, refine_config=rc, progress=True
        )
        seconds = time.perf_counter() - t0
        out["model"] = summary["model"]
        row = summary[f"refined_{args.steps}"]
        out["variants"].append(
            {"rate_scale": scale, "perceptual_weight": perceptual, "field_factors": fields, "seconds": seconds, **row}
        )
        field_text = "".join(f", {k} x{v:g}" for k, v in fields.items())
        print(
            f"rates x{scale:g}{field_text}, perceptual {perceptual:g}: PSNR {row['psnr']:.2f} SSIM {row['ssim']:.3f} "
            f"LPIPS {row['lpips']:.3f} inputs {row['input_psnr']:.2f} ({seconds:.0f} s; model "
            f"{summary['model']['psnr']:.2f} / {summary['model']['lpips']:.3f})",
            flush=True,
        )
        with open(path, "w") as f:
            json.dump(out, f, indent=1)
    print(f"wrote {path}")


if __name__ == "__main__":
    main()

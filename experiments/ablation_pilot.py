"""Pilot of the ablation notebooks' ``cpu`` scale: how many steps before rows can be told apart.

Run:  python experiments/ablation_pilot.py --budgets 200,400,600 --seeds 3
      (about 15 minutes per row on a 2-core CPU; writes experiments/results/ablations/pilot_cpu.json)

Trains each table's chosen row (Table 4: K16 F32 canvas 0.5 with an LLG decoder; Tables 5
and 6: LLGGG, S=2; Table 7: LLGGG with the depth loss) at the cpu scale of
``llrmpp_jax.ablation`` for the largest budget, once per seed, scoring the held-out scenes
after each budget. Prints, per budget, the mean held-out PSNR / LPIPS with the seed spread
and 95% interval next to the untrained model and the two baselines (mean colour, nearest
view): the cpu scale's step count is the smallest budget at which every chosen row is
clearly (interval clear of) above all three.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import time
from dataclasses import replace

import jax
from git_worktree import revision

from llrmpp_jax import ablation as A
from llrmpp_jax.metrics import load_lpips_params

# The chosen row of each table: name -> (decoder blocks, renders depth). The cpu base is
# already the chosen head (K16 F32, canvas 0.5) and decoder (LLGGG, S=2).
CHOSEN = {
    "table4 K16 F32 0.5 (LLG)": ("LLG", False),
    "table5/6 LLGGG S=2": ("LLGGG", False),
    "table7 Ours (depth)": ("LLGGG", True),
}


def chosen_row(name: str, scale: A.Scale) -> tuple[A.Scale, A.Variant]:
    """The chosen row ``name`` of :data:`CHOSEN`, as its notebook builds it at ``scale``."""
    blocks, depth = CHOSEN[name]
    if depth:
        scale = dataclasses.replace(scale, base=replace(scale.base, outputs=("rgb", "depth")))
    build = lambda base: replace(base, decoder=replace(base.decoder, blocks=blocks))  # noqa: E731
    return scale, A.Variant({"row": name}, build, {}, chosen=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=(__doc__ or "").split("\n")[0])
    parser.add_argument("--budgets", default="200,400,600", help="comma-separated step counts to score")
    parser.add_argument("--seeds", type=int, default=3, help="seeds per row (init and data order)")
    parser.add_argument(
        "--rows", default="table5/6 LLGGG S=2", help="comma-separated chosen rows to pilot, of: " + "; ".join(CHOSEN)
    )
    parser.add_argument(
        "--out",
        help="JSON file to write (default: experiments/results/ablations/pilot_cpu.json)",
        default=os.path.join(os.path.dirname(os.path.abspath(__file__)), "results", "ablations", "pilot_cpu.json"),
    )
    args = parser.parse_args()
    budgets = sorted(int(b) for b in args.budgets.split(","))
    if args.seeds < 1 or budgets[0] < 1:
        parser.error(f"--seeds and --budgets must be >= 1, got {args.seeds} and {budgets}")
    base_scale = dataclasses.replace(A.make_scale("cpu", paper_views=4), steps=budgets[-1], seeds=args.seeds)
    lp = load_lpips_params()
    record = {"scale": str(base_scale), "budgets": budgets, "machine": A.machine(), "commit": revision(), "rows": {}}
    t0 = time.perf_counter()
    unknown = [r for r in args.rows.split(",") if r not in CHOSEN]
    if unknown:
        parser.error(f"--rows: unknown {unknown}; known: {list(CHOSEN)}")
    for name in args.rows.split(","):
        scale, variant = chosen_row(name, base_scale)
        cfg = variant.build(scale.base)  # pyright: ignore[reportOptionalCall] -- every CHOSEN row has a build
        samples = A.held_out_samples(cfg, scale)
        per_budget: dict[int, list[dict]] = {b: [] for b in budgets}
        seconds = []
        for seed in range(scale.seeds):
            trained = A.train(cfg, scale, variant, seed, snapshots=budgets)
            seconds.append(trained.seconds)
            for b in budgets:
                per_budget[b].append(A.row_scores(trained.snapshots[b], cfg, samples, lp))
            print(
                f"{name} seed {seed}: {trained.seconds:.0f} s, PSNR by budget "
                + ", ".join(f"{b}: {per_budget[b][-1]['psnr']:.2f}" for b in budgets),
                flush=True,
            )
        refs = A.references(cfg, scale, samples, lp)
        record["rows"][name] = {
            "train_s": seconds,
            "references": refs,
            "budgets": {str(b): A.summarise(per_budget[b]) for b in budgets},
        }
        print(f"\n{name} ({sum(seconds) / len(seconds):.0f} s per seed for {budgets[-1]} steps)")
        print("| steps | PSNR (± 95%) | std | LPIPS |")
        print("|---|---|---|---|")
        for b in budgets:
            s = record["rows"][name]["budgets"][str(b)]
            print(f"| {b} | {s['psnr']:.2f} ± {s['psnr_ci']:.2f} | {s['psnr_std']:.2f} | {s['lpips']:.3f} |")
        for ref in refs:
            print(f"| {ref['name']} | {ref['psnr']:.2f} | | {ref['lpips']:.3f} |")
        record["wall_s"] = time.perf_counter() - t0
        os.makedirs(os.path.dirname(args.out) or ".", exist_ok=True)
        with open(args.out, "w") as f:
            json.dump(record, f, indent=1, default=float)
    print(f"\nwrote {args.out} ({record['wall_s'] / 60:.1f} min, {jax.devices()[0].platform})")


if __name__ == "__main__":
    main()

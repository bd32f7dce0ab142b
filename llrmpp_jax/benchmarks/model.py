"""The paper's Table-1 figures on this device: reconstruction time at V inputs and render
frames per second, with compile time, peak memory, FLOPs and the fraction of the card's
bf16 peak, as JSON (:mod:`llrmpp_jax.benchmarks.paper`); or a profile of one reconstruct +
render (``--profile``).

Run:
    python -m llrmpp_jax.benchmarks.model --scale paper --out runs/bench_model.json  # one GPU: V = 16/32/64 at 544x960
    python -m llrmpp_jax.benchmarks.model --scale cpu  # config.tiny(), seconds
    python -m llrmpp_jax.benchmarks.model --scale paper --profile --out runs/profile_model.json   # 8 inputs, one render

``llrmpp bench --scale cpu|paper --only model`` runs the first two. ``--views`` (e.g.
``16,32``) and ``--size`` (``HxW``) replace the scale's; ``--profile`` takes one view
count (default the scale's, 8 at paper scale) and prints the profile's Markdown tables.
"""

from __future__ import annotations

import argparse
import json
import os
import sys

from llrmpp_jax.benchmarks.paper import (
    bench_scale,
    check_case,
    parse_hw,
    parse_views,
    profile_markdown,
    profile_reconstruct_render,
    run_table1,
)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=(__doc__ or "").split("\n")[0])
    ap.add_argument("--scale", default="paper", help="paper (one accelerator) or cpu (config.tiny())")
    ap.add_argument("--views", default=None, help="input view counts, comma-separated (default: the scale's)")
    ap.add_argument("--size", default=None, help="HxW of every view (default: the scale's, 544x960 at paper scale)")
    ap.add_argument("--profile", action="store_true", help="profile one reconstruct + render instead of timing")
    ap.add_argument("--out", default=os.path.join("runs", "bench", "bench_model.json"), help="JSON file written")
    args = ap.parse_args(argv)
    try:  # bad input: one line, before any work
        views = parse_views(args.views) if args.views else None
        size = parse_hw(args.size) if args.size else None
        scale = bench_scale(args.scale)
        if args.profile and views is not None and len(views) != 1:
            raise ValueError(f"bench: --profile takes one view count, got --views {args.views}")
        check_case(scale.model, views or scale.views, *(size or (scale.height, scale.width)))
    except ValueError as e:
        print(e, file=sys.stderr)
        return 2
    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)

    def save(result: dict) -> None:
        with open(args.out, "w") as f:
            json.dump(result, f, indent=1)

    if args.profile:
        result = profile_reconstruct_render(args.scale, views[0] if views else None, size)
        print(profile_markdown(result["profile"]))
        save(result)
    else:  # written after every case: a time limit keeps the finished ones
        run_table1(args.scale, views, size, log=lambda line: print(line, flush=True), save=save)
    print("wrote", args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Poses from the beer capture's photos alone, against the capture's shipped COLMAP poses.

    python experiments/poses_beer.py --out experiments/results/poses   # ~5 min on 2 cores

Runs ``llrmpp poses`` (``estimate_poses``) on ``../shared/data/beer/images`` twice, with the
default ``--matcher auto`` and with ``--matcher exhaustive``, into a temporary folder, and
writes ``beer.json``:

* each run's report (registered, phases, matchers tried, the continuity breaks of its model);
* the shipped model's own continuity breaks, checked against the auto run's database;
* agreement with the shipped poses (``pose_check.compare_poses``: RANSAC similarity, 2 degrees
  and 2% of the camera extent), over all frames and per unbroken run of the shipped model
  (each run aligned on its own, so a fold of the reference between runs does not count);

and ``beer_same_place.png``: for four frames of the capture's first part, the frame of a later
part that each model puts nearest to it (camera centre and viewing direction), side by side:
row 1 our auto run, row 2 the shipped model. Frames a correct model puts at the same place
show the same background.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile

import numpy as np
import pycolmap

from llrmpp_jax.capture.pose_check import camera_poses, compare_poses, continuity_breaks
from llrmpp_jax.capture.poses import PosesConfig, estimate_poses
from llrmpp_jax.data.image_io import read_image, write_image


def runs_between_breaks(names: list[str], breaks) -> list[list[str]]:
    """``names`` (sorted) cut after each break's first image."""
    cuts = {b.first for b in breaks}
    runs, current = [], []
    for n in names:
        current.append(n)
        if n in cuts:
            runs.append(current)
            current = []
    return runs + ([current] if current else [])


def nearest_later(poses, name: str, min_gap: int) -> str:
    """The image at least ``min_gap`` names later whose camera is nearest in centre and
    viewing direction (centre distance over the cameras' extent plus the angle in radians)."""
    names = sorted(poses)
    centres = np.array([poses[n][1] for n in names])
    extent = np.linalg.norm(centres.max(0) - centres.min(0))
    i = names.index(name)
    r0, c0 = poses[name]

    def cost(n):
        r, c = poses[n]
        angle = np.arccos(np.clip(r0[:, 2] @ r[:, 2], -1.0, 1.0))
        return np.linalg.norm(c - c0) / extent + angle

    return min(names[i + min_gap :], key=cost)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    ap.add_argument("--capture", default="../shared/data/beer", help="capture with images/ and sparse/0/")
    ap.add_argument("--out", default="experiments/results/poses", help="folder for beer.json and the picture")
    args = ap.parse_args(argv)
    shipped_model = pycolmap.Reconstruction(os.path.join(args.capture, "sparse", "0"))
    shipped = camera_poses(shipped_model)
    result: dict = {"capture": args.capture, "frames": len(shipped)}
    with tempfile.TemporaryDirectory() as tmp:
        models = {}
        for matcher in ("auto", "exhaustive"):
            out = os.path.join(tmp, matcher)
            report = estimate_poses(
                os.path.join(args.capture, "images"),
                out,
                PosesConfig(matcher=matcher),
                progress=lambda s: print(s, file=sys.stderr),
            )
            model = pycolmap.Reconstruction(os.path.join(out, "sparse", "0"))
            poses = camera_poses(model)
            entry = {
                "registered": report.registered,
                "given": report.given,
                "matchers_tried": report.matchers_tried,
                "kept": report.matcher,
                "breaks": list(report.breaks),
                "seconds": report.seconds,
                "mean_reprojection_error_px": report.mean_reprojection_error_px,
                "vs_shipped": compare_poses(poses, shipped).summary(),
            }
            models[matcher] = (poses, os.path.join(out, "database.db"))
            result[matcher] = entry
        auto_poses, auto_db = models["auto"]
        shipped_breaks = continuity_breaks(shipped_model, auto_db)
        runs = runs_between_breaks(sorted(shipped), shipped_breaks)
        per_run = []
        for run in runs:
            sub = {n: shipped[n] for n in run}
            for matcher, (poses, _) in models.items():
                summary = compare_poses(poses, sub).summary()
                per_run.append({"run": f"{run[0]}..{run[-1]}", "matcher": matcher, **summary})
        result["shipped_breaks"] = [str(b) for b in shipped_breaks]
        result["vs_shipped_per_run"] = per_run
        for matcher in models:
            rows = [r for r in per_run if r["matcher"] == matcher]
            result[matcher]["vs_shipped_runs_fraction_within"] = sum(r["within"] for r in rows) / sum(
                r["frames"] for r in rows
            )

        firsts = ["0004.jpg", "0012.jpg", "0014.jpg", "0020.jpg"]
        rows = []
        for poses in (auto_poses, shipped):
            tiles = []
            for name in firsts:
                other = nearest_later(poses, name, 15)
                for n in (name, other):
                    tiles.append(read_image(os.path.join(args.capture, "images", n))[::6, ::6])
            rows.append(np.concatenate(tiles, axis=1))
        result["same_place_pairs"] = {
            "auto": [[n, nearest_later(auto_poses, n, 15)] for n in firsts],
            "shipped": [[n, nearest_later(shipped, n, 15)] for n in firsts],
        }
    os.makedirs(args.out, exist_ok=True)
    write_image(os.path.join(args.out, "beer_same_place.png"), np.concatenate(rows, axis=0))
    with open(os.path.join(args.out, "beer.json"), "w") as f:
        json.dump(result, f, indent=1)
    print(json.dumps({k: result[k] for k in ("shipped_breaks",)}, indent=1))
    for matcher in models:
        r = result[matcher]
        print(
            f"{matcher}: kept {r['kept']}, breaks {len(r['breaks'])}, within (all) "
            f"{r['vs_shipped']['fraction_within']:.2f}, within (per shipped run) "
            f"{r['vs_shipped_runs_fraction_within']:.2f}, seconds {r['seconds']}"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

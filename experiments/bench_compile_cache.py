"""Benchmark of the persistent compilation cache: each command run twice on this machine, the
first time with an empty cache folder (cold), the second with what the first left (warm).

Each run is a fresh process (``llrmpp ... --compile-cache DIR``) with ``LLRMPP_COMPILE_REPORT``
set, so the CLI writes the command's compile count, how many came from the cache, their
summed compile-or-load seconds and the command's wall time. Commands, on a capture from
``../shared/data`` (default beer) with the shipped model:

* ``reconstruct`` of ``--num-inputs`` views at ``--size``;
* ``render --path spline --frames 12`` of that reconstruction;
* ``refine --steps 3`` of it;
* the viewer's first frame (``ViewRenderer.compile`` + ``render`` at the viewer's default size,
  what ``llrmpp view`` does before the page shows a picture);
* ``llrmpp demo`` (with ``--demo``: ~5 minutes a run).

Writes JSON (rows: command, run, wall_s, compile_s, programs, from_cache, the 1-minute load
average when the run ended; the cache's size after each command's runs) and prints a
Markdown table.

Run:  python experiments/bench_compile_cache.py --demo --out experiments/results/bench_compile_cache.json
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import subprocess
import sys
import tempfile
import time

HERE = os.path.dirname(os.path.abspath(__file__))
SHARED = os.path.abspath(os.path.join(HERE, "..", "..", "shared", "data"))

_VIEWER_FRAME = """
import json, sys, time
from llrmpp_jax import compile_cache
compile_cache.enable(sys.argv[2])
t0 = time.perf_counter()
with compile_cache.CompileWatch() as w:  # what `llrmpp view --gaussians` does before the page shows a picture
    from llrmpp_jax.capture import load_gs
    from llrmpp_jax.params_io import load_params
    from llrmpp_jax.viewer.render import ViewKey, ViewRenderer, viewport_camera
    from llrmpp_jax.viewer.scene import saved_view_scene
    from llrmpp_jax.viewer.server import ViewerSettings
    saved = load_gs(sys.argv[1])
    params, cfg = load_params(sys.argv[3], saved.model)
    scene = saved_view_scene(saved)
    cameras = (scene.input_c2w, scene.input_intrinsics, scene.input_hw)
    renderer = ViewRenderer(params, cfg, scene.gaussians, cameras=cameras)
    h, w_, k = viewport_camera(0.9, 16 / 9, ViewerSettings().height, cfg.size_multiple)
    frame = renderer.render(ViewKey(h, w_, "rgb", renderer.max_partitions), scene.input_c2w[0], k)
json.dump({"command": "view (first frame)", "status": 0, "wall_s": time.perf_counter() - t0,
           "programs": w.programs, "from_cache": w.hits, "compile_s": w.seconds}, open(sys.argv[4], "w"))
"""


def _run(argv: list[str], report: str, log: str) -> dict:
    env = {**os.environ, "LLRMPP_COMPILE_REPORT": report}
    t0 = time.perf_counter()
    with open(log, "a") as f:
        proc = subprocess.run(argv, env=env, stdout=f, stderr=subprocess.STDOUT)
    if proc.returncode != 0:
        raise SystemExit(f"{' '.join(argv)} exited {proc.returncode}; see {log}")
    with open(report) as f:
        row = json.load(f)
    row["process_s"] = time.perf_counter() - t0  # wall time including Python and JAX start-up
    row["load_average_1min"] = os.getloadavg()[0]  # at the end: a shared machine slows both runs
    return row


def _size(folder: str) -> int:
    from llrmpp_jax.compile_cache import usage

    return usage(folder)[1]


def main() -> None:
    ap = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    ap.add_argument("--scene", default=os.path.join(SHARED, "beer"), help="capture folder")
    ap.add_argument("--checkpoint", default="pretrained:small", help="model weights")
    ap.add_argument("--num-inputs", type=int, default=32, help="input views of the reconstruction")
    ap.add_argument("--size", default="256", help="view size (H or HxW)")
    ap.add_argument("--demo", action="store_true", help="also `llrmpp demo` twice (~5 minutes a run)")
    ap.add_argument("--work", default=None, help="scratch folder (default: a temporary one)")
    ap.add_argument("--out", default=os.path.join(HERE, "results", "bench_compile_cache.json"), help="JSON path")
    args = ap.parse_args()

    work = args.work or tempfile.mkdtemp(prefix="bench_compile_cache_")
    os.makedirs(work, exist_ok=True)
    llrmpp = [sys.executable, "-m", "llrmpp_jax.cli"]
    gs = os.path.join(work, "scene.gs")
    commands = {
        "reconstruct": [
            *("reconstruct", "--checkpoint", args.checkpoint, "--scene", args.scene),
            *("--num-inputs", str(args.num_inputs), "--size", args.size, "--repeats", "1", "--out", gs),
        ],
        "render --path spline": [
            *("render", "--gaussians", gs, "--checkpoint", args.checkpoint, "--path", "spline"),
            *("--frames", "12", "--quiet", "--out", os.path.join(work, "frames")),
        ],
        "refine --steps 3": [
            *("refine", "--gaussians", gs, "--checkpoint", args.checkpoint, "--steps", "3", "--quiet"),
            *("--out", os.path.join(work, "refined.gs")),
        ],
        "view (first frame)": None,
    }
    if args.demo:
        commands["demo"] = ["demo", "--out", os.path.join(work, "demo")]
    rows, sizes = [], {}
    for name, argv in commands.items():
        cache = os.path.join(work, "cache", name.split()[0])
        shutil.rmtree(cache, ignore_errors=True)
        for run in ("cold", "warm"):
            report = os.path.join(work, f"report_{len(rows)}.json")
            if argv is None:
                cmd = [sys.executable, "-c", _VIEWER_FRAME, gs, cache, args.checkpoint, report]
            else:
                cmd = [*llrmpp, *argv, "--compile-cache", cache]
            row = _run(cmd, report, os.path.join(work, "log.txt"))
            row.update(name=name, run=run)
            rows.append(row)
            print(f"{name} {run}: {row['wall_s']:.1f} s, compile {row['compile_s']:.1f} s", flush=True)
        sizes[name] = _size(cache)
    import jax

    result = {
        "machine": {"cpu": platform.processor() or platform.machine(), "cores": os.cpu_count(), "jax": jax.__version__},
        "scene": os.path.basename(args.scene.rstrip("/")),
        "num_inputs": args.num_inputs,
        "size": args.size,
        "rows": rows,
        "cache_bytes": sizes,
    }
    with open(args.out, "w") as f:
        json.dump(result, f, indent=1)
    print("\n| command | cold: wall / compile (s) | warm: wall / compile (s) | compile ratio | cache MiB |")
    print("|---|---|---|---|---|")
    for name in commands:
        cold, warm = (r for r in rows if r["name"] == name)
        ratio = cold["compile_s"] / max(warm["compile_s"], 1e-9)
        print(
            f"| {name} | {cold['wall_s']:.1f} / {cold['compile_s']:.1f} | {warm['wall_s']:.1f} / "
            f"{warm['compile_s']:.2f} ({warm['from_cache']}/{warm['programs']} cached) | {ratio:.0f}x | "
            f"{sizes[name] / 2**20:.1f} |"
        )
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()

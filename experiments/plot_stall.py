"""Figures of the stall probe's files (``experiments/ablation_stall_probe.py``): one column per
``--column``, each line one (file, seed) run; rows: training loss and pre-clip gradient norm
per step, and with ``--snap KEY`` that Gaussian statistic at the probe's snapshots.

Run (from the repository root; the figures of notebooks/README.md, "Stalled seeds"):
    python experiments/plot_stall.py experiments/results/ablations/stall/lr.png \\
        --column "Table 6 S=2 row, seed 2 (stalled at lr 2e-3)" \\
            s2_lr2e-3.json:2:"lr 2e-3" s2_lr1e-3.json:2:"lr 1e-3" \\
        --column "Table 6 S=2 row, seed 3 (healthy at lr 2e-3)" \\
            s2_lr2e-3.json:3:"lr 2e-3" s2_lr1e-3.json:3:"lr 1e-3"
    python experiments/plot_stall.py experiments/results/ablations/stall/depth.png --snap dist_gt9 \\
        --column "Table 7, Ours w/o aux losses" t7_noaux.json:6:"seed 6" t7_noaux.json:3:"seed 3" \\
        --column "Table 7, Ours" t7_aux.json:0:"seed 0" t7_aux.json:7:"seed 7"
File names are relative to the figure's folder. Loss curves are drawn as they are (no
smoothing); a legend gives each run's held-out PSNR.
"""

import argparse
import json
import os

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

SNAP_LABELS = {
    "dist_gt9": "Gaussians > 9 units from the inputs",
    "op_mean": "mean opacity",
    "logscale_mean": "mean log-scale",
    "op_lt01": "opacity < 0.01",
}


def parse_run(spec: str) -> tuple[str, str, str]:
    parts = spec.split(":", 2)
    if len(parts) != 3:
        raise SystemExit(f"a run is FILE:SEED:LABEL, got {spec!r}")
    return parts[0], parts[1], parts[2]


def main(out: str, columns: list[tuple[str, list[str]]], snap: str | None) -> str:
    folder = os.path.dirname(out)
    rows = 3 if snap else 2
    fig, axes = plt.subplots(rows, len(columns), figsize=(5.5 * len(columns), 3 * rows), squeeze=False)
    for col, (title, runs) in enumerate(columns):
        axes[0, col].set_title(title)
        for spec in runs:
            name, seed, label = parse_run(spec)
            with open(os.path.join(folder, name)) as f:
                probe = json.load(f)
            if seed not in probe:
                raise SystemExit(f"{name}: no seed {seed} (has {sorted(probe)})")
            r = probe[seed]
            axes[0, col].plot(r["losses"], lw=0.8, label=f"{label}: {r['eval']['psnr']:.2f} dB held out")
            axes[1, col].plot(r["grad_norms"], lw=0.8, label=label)
            if snap:
                steps = sorted(r["snap"], key=int)
                axes[2, col].plot([int(s) for s in steps], [r["snap"][s][snap] for s in steps], "o-", label=label)
        axes[0, col].set_ylabel("training loss")
        axes[1, col].set_ylabel("gradient norm (pre-clip)")
        for ax in axes[:2, col]:
            ax.set_yscale("log")
        if snap:
            axes[2, col].set_ylabel(SNAP_LABELS.get(snap, snap))
        axes[-1, col].set_xlabel("step")
        for ax in axes[:, col]:
            ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(out, dpi=100)
    return out


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=(__doc__ or "").split("\n\n")[0])
    parser.add_argument("out", help="the figure (PNG); run files are read from its folder")
    parser.add_argument(
        "--column",
        nargs="+",
        action="append",
        required=True,
        metavar="TITLE RUN",
        help="a column: its title, then FILE:SEED:LABEL for each run",
    )
    parser.add_argument("--snap", help="also plot this snapshot statistic (e.g. dist_gt9)")
    args = parser.parse_args()
    cols = []
    for c in args.column:
        if len(c) < 2:
            raise SystemExit(f"--column needs a title and at least one run, got {c}")
        cols.append((c[0], c[1:]))
    print(main(args.out, cols, args.snap))

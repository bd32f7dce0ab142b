"""Figure for notebooks/README.md, "What the guard did not fix: the learning rate": training
loss and pre-clip gradient norm per step of the Table 6 S=2 row's seeds 2 (stalled) and 3
(healthy) at the peak rates 2e-3 and 1e-3, from the stall probe's two files.

Run (from the repository root, after the two probe runs named in that section):
    python experiments/plot_stall_lr.py experiments/results/ablations/stall
which reads ``s2_lr2e-3.json`` and ``s2_lr1e-3.json`` there and writes ``lr.png`` beside them.
"""
import json
import os
import sys

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

RUNS = {"2e-3": "s2_lr2e-3.json", "1e-3": "s2_lr1e-3.json"}
SEEDS = {"2": "stalled at lr 2e-3", "3": "healthy at lr 2e-3"}


def main(folder: str) -> str:
    runs = {}
    for lr, name in RUNS.items():
        with open(os.path.join(folder, name)) as f:
            runs[lr] = json.load(f)
    fig, axes = plt.subplots(2, len(SEEDS), figsize=(11, 6), sharex=True)
    for col, (seed, state) in enumerate(SEEDS.items()):
        axes[0, col].set_title(f"Table 6 S=2 row, seed {seed} ({state})")
        for lr, run in runs.items():
            if seed not in run:
                raise SystemExit(f"{RUNS[lr]}: no seed {seed} (has {sorted(run)})")
            r = run[seed]
            axes[0, col].plot(r["losses"], lw=0.8, label=f"lr {lr}: {r['eval']['psnr']:.2f} dB held out")
            axes[1, col].plot(r["grad_norms"], lw=0.8, label=f"lr {lr}")
        axes[0, col].set_ylabel("training loss")
        axes[1, col].set_ylabel("gradient norm (pre-clip)")
        axes[1, col].set_xlabel("step")
        for ax in axes[:, col]:
            ax.set_yscale("log")
            ax.legend(fontsize=7)
    fig.tight_layout()
    out = os.path.join(folder, "lr.png")
    fig.savefig(out, dpi=100)
    return out


if __name__ == "__main__":
    if len(sys.argv) != 2:
        raise SystemExit("usage: python experiments/plot_stall_lr.py FOLDER")
    print(main(sys.argv[1]))

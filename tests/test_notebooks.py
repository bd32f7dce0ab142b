"""The ablation notebooks (paper Tables 4-7): paired .ipynb in sync, rows and paper numbers
as printed in the paper's .tex, and a smoke run per notebook.

* Sync: the .ipynb's cells (type and source) equal jupytext's reading of the percent .py.
* Rows: each notebook runs in-process with ``LLRMPP_NOTEBOOK_ROWS=none`` (builds its
  variant list, trains nothing); its row labels, the paper's numbers and the chosen row
  must equal the table parsed from ``paper/long-lrm-pp.tex`` (independent oracle).
* Smoke run (slow): the .py runs as a script in a fresh process (strict dtype and rank
  promotion, 2 train steps, one or two rows so the file stays within a few minutes) and
  must produce one result and one table line per selected row with finite metrics.
  Compile time dominates (~4.5 min for the four on 2 shared cores); the process uses XLA's
  lowest optimisation level and a persistent compilation cache in the system temp folder,
  so later runs take about half as long.
"""

import json
import math
import os
import re
import runpy
import subprocess
import sys
import tempfile

import pytest

from conftest import shared_path

ROOT = os.path.abspath(os.path.join(os.path.dirname(__file__), ".."))
NB_DIR = os.path.join(ROOT, "notebooks")

# notebook -> (label of its table in the .tex, its label columns, rows run by the smoke test)
NOTEBOOKS = {
    "table4_feature_splat": ("tb:featsplat", ("K", "F", "canvas"), "4"),  # canvas 1.0: r = 1
    "table5_decoder": ("tb:decoder", ("splat", "blocks", "dim"), "0"),  # colour Gaussians
    "table6_partitions": ("tb:featsplit", ("S",), "0"),  # S = 1
    "table7_depth_losses": ("tb:dep_ab", ("method",), "0,3"),  # a row that cannot run + depth
}
# Paper columns in .tex order (Table 7's method names are LaTeX; its label is compared by order).
PAPER_KEYS = {
    "tb:featsplat": ("PSNR",),
    "tb:decoder": ("PSNR",),
    "tb:featsplit": ("PSNR", "SSIM", "LPIPS", "PSNR 540p", "SSIM 540p", "LPIPS 540p", "recon 540p", "FPS 540p"),
    "tb:dep_ab": ("PSNR", "SSIM", "LPIPS", "Abs Diff", "delta<1.25"),
}


def paper_table(label: str) -> list[tuple[list[str], bool]]:
    """Rows ``(cells, chosen)`` of the tabular labelled ``label`` in the paper's .tex."""
    tex = open(shared_path("paper", "long-lrm-pp.tex"), encoding="utf-8").read()
    end = tex.index(f"\\label{{{label}}}")
    begin = tex.rindex("\\begin{tabular}", 0, end)
    body = tex[begin:end].split("\\midrule")[1].split("\\bottomrule")[0]
    rows = []
    for line in body.split("\\\\"):
        line = line.replace("\\hdashline", "").strip()
        if not line:
            continue
        chosen = "\\rowcolor{chosen}" in line
        line = re.sub(r"\\(rowcolor|cellcolor)\{[^}]*\}", "", line)
        rows.append(([c.strip() for c in line.split("&")], chosen))
    return rows


def test_every_notebook_is_tested():
    names = {f[:-3] for f in os.listdir(NB_DIR) if f.endswith(".py") and not f.startswith("_")}
    assert names == set(NOTEBOOKS)
    assert {f[:-6] for f in os.listdir(NB_DIR) if f.endswith(".ipynb")} == names


@pytest.mark.parametrize("name", sorted(NOTEBOOKS))
def test_ipynb_in_sync_with_py(name):
    jupytext = pytest.importorskip("jupytext")
    py = jupytext.read(os.path.join(NB_DIR, name + ".py"), fmt="py:percent")
    nb = jupytext.read(os.path.join(NB_DIR, name + ".ipynb"))
    cells = lambda n: [(c.cell_type, c.source) for c in n.cells]  # noqa: E731
    assert cells(nb) == cells(py), f"{name}.ipynb is stale: run `jupytext --to ipynb notebooks/{name}.py`"
    assert all(not c.get("outputs") for c in nb.cells), f"{name}.ipynb holds outputs; regenerate it"


@pytest.mark.parametrize("name", sorted(NOTEBOOKS))
def test_rows_match_paper_table(name, monkeypatch, capsys):
    label, label_keys, _ = NOTEBOOKS[name]
    monkeypatch.setenv("LLRMPP_NOTEBOOK_ROWS", "none")
    monkeypatch.setenv("LLRMPP_NOTEBOOK_SCALE", "smoke")
    monkeypatch.syspath_prepend(NB_DIR)
    g = runpy.run_path(os.path.join(NB_DIR, name + ".py"))
    assert g["results"] == []
    variants = g["VARIANTS"]
    rows = paper_table(label)
    assert len(variants) == len(rows)
    keys = PAPER_KEYS[label]
    for v, (cells, chosen) in zip(variants, rows, strict=True):
        n_labels = len(cells) - len(keys)
        if label != "tb:dep_ab":
            assert tuple(v.labels[k] for k in label_keys) == tuple(cells[:n_labels])
        assert tuple(v.paper[k] for k in keys) == tuple(cells[n_labels:])
        assert v.chosen == chosen
    assert "|" in capsys.readouterr().out  # the (empty) table's header was printed


def _finite(x) -> bool:
    return isinstance(x, (int, float)) and math.isfinite(x)


@pytest.mark.slow
@pytest.mark.parametrize("name", sorted(NOTEBOOKS))
def test_smoke_run(name, tmp_path):
    label, label_keys, rows = NOTEBOOKS[name]
    out = tmp_path / "results.json"
    runner = (
        "import json, runpy, sys\n"
        f"sys.path.insert(0, {NB_DIR!r})\n"
        f"g = runpy.run_path({os.path.join(NB_DIR, name + '.py')!r}, run_name='__main__')\n"
        "labels = [v.labels for v in g['VARIANTS']]\n"
        f"json.dump({{'results': g['results'], 'labels': labels}}, open({str(out)!r}, 'w'))\n"
    )
    env = dict(
        os.environ,
        LLRMPP_NOTEBOOK_SCALE="smoke",
        LLRMPP_NOTEBOOK_STEPS="2",
        LLRMPP_NOTEBOOK_ROWS=rows,
        JAX_PLATFORMS="cpu",
        JAX_NUMPY_DTYPE_PROMOTION="strict",
        JAX_NUMPY_RANK_PROMOTION="raise",
        JAX_COMPILATION_CACHE_DIR=os.path.join(tempfile.gettempdir(), "llrmpp-notebook-xla-cache"),
        JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS="0",
        XLA_FLAGS="--xla_backend_optimization_level=0 --xla_llvm_disable_expensive_passes=true",
    )
    proc = subprocess.run([sys.executable, "-c", runner], cwd=ROOT, env=env, capture_output=True, text=True,
                          timeout=600)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-5000:]
    data = json.loads(out.read_text())
    results, labels = data["results"], data["labels"]
    wanted = [int(r) for r in rows.split(",")]
    assert [r["row"] for r in results] == wanted
    table_lines = [ln for ln in proc.stdout.splitlines() if ln.startswith("| ")][1:]  # minus the header
    assert len(table_lines) == len(wanted)
    for r, line in zip(results, table_lines, strict=True):
        assert {k: r[k] for k in label_keys} == labels[r["row"]]
        cells = [c.strip() for c in line.strip("|").split("|")]
        assert cells[1:1 + len(label_keys)] == [r[k] for k in label_keys]
        if r["status"] != "ok":
            assert r["status"].startswith("not run: ") and f"row {r['row']}: not run" in proc.stdout
            continue
        assert f"{r['psnr']:.2f}" in cells  # the printed table shows this row's PSNR
        for k in ("psnr", "ssim", "final_loss", "recon_s", "render_s"):
            assert _finite(r[k]), (k, r[k])
        assert -1.0 <= r["ssim"] <= 1.0 and r["recon_s"] > 0 and r["render_s"] > 0
        assert r["params"] > 0 and r["gaussians"] > 0
        if label == "tb:dep_ab":
            assert _finite(r["abs_diff"]) and 0.0 <= r["delta_1_25"] <= 1.0

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
* Workers (slow): one row trained on a pool of 2 worker processes scores as the same
  trainings run in the notebook's own process.
"""

import dataclasses
import json
import math
import os
import re
import runpy
import subprocess
import sys
import tempfile
from dataclasses import replace

import numpy as np
import pytest

from tests.helpers.environment import QUICK_XLA_FLAGS, ROOT, shared_path

NB_DIR = os.path.join(ROOT, "notebooks")

# notebook -> (label of its table in the .tex, its label columns, rows run by the smoke test)
NOTEBOOKS = {
    "table4_feature_splat": ("tb:featsplat", ("K", "F", "canvas"), "4"),  # canvas 1.0: r = 1
    "table5_decoder": ("tb:decoder", ("splat", "blocks", "dim"), "0"),  # colour Gaussians
    "table6_partitions": ("tb:featsplit", ("S",), "0"),  # S = 1
    "table7_depth_losses": ("tb:dep_ab", ("method",), "0,3"),  # Long-LRM 2DGS (2D colour Gaussians) + Ours
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
    assert cells(nb) == cells(py), f"{name}.ipynb is stale: run `make notebooks` (or jupytext --to ipynb)"


@pytest.mark.parametrize("name", sorted(NOTEBOOKS))
def test_rows_match_paper_table(name, monkeypatch, capsys, tmp_path):
    label, label_keys, _ = NOTEBOOKS[name]
    monkeypatch.setenv("LLRMPP_NOTEBOOK_ROWS", "none")
    monkeypatch.setenv("LLRMPP_NOTEBOOK_SCALE", "smoke")
    monkeypatch.setenv("LLRMPP_NOTEBOOK_OUT", str(tmp_path))
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
    for o in g["ORDERINGS"]:  # each claim names two rows, in the paper's direction
        a, b = variants[o.better].paper, variants[o.worse].paper
        key = {"psnr": "PSNR", "ssim": "SSIM", "lpips": "LPIPS", "abs_diff": "Abs Diff", "delta_1_25": "delta<1.25"}[
            o.metric
        ]
        higher = o.metric in ("psnr", "ssim", "delta_1_25")
        assert (float(a[key]) > float(b[key])) == higher, o.text


def _finite(x) -> bool:
    return isinstance(x, (int, float)) and math.isfinite(x)


def _run_notebook(name: str, tmp_path, rows: str, **env: str) -> tuple[subprocess.CompletedProcess, dict]:
    """Run ``notebooks/{name}.py`` as a script at the smoke scale (2 seeds, 2 steps, the
    ``rows``), results saved under ``tmp_path/saved``; returns the process and its results,
    labels and orderings."""
    tmp_path.mkdir(parents=True, exist_ok=True)
    out = tmp_path / "results.json"
    runner = (
        "import json, runpy\n"
        f"g = runpy.run_path({os.path.join(NB_DIR, name + '.py')!r}, run_name='__main__')\n"
        "labels = [v.labels for v in g['VARIANTS']]\n"
        f"json.dump({{'results': g['results'], 'labels': labels, 'orderings': g['comparisons']}}, "
        f"open({str(out)!r}, 'w'))\n"
    )
    env = dict(
        os.environ,
        LLRMPP_NOTEBOOK_SCALE="smoke",
        LLRMPP_NOTEBOOK_STEPS="2",
        LLRMPP_NOTEBOOK_ROWS=rows,
        LLRMPP_NOTEBOOK_SEEDS="2",
        LLRMPP_NOTEBOOK_OUT=str(tmp_path / "saved"),
        LLRMPP_NOTEBOOK_REVISION="abc1234+dirty",  # what notebooks/_execute.py passes in
        MPLBACKEND="Agg",
        JAX_PLATFORMS="cpu",
        JAX_NUMPY_DTYPE_PROMOTION="strict",
        JAX_NUMPY_RANK_PROMOTION="raise",
        JAX_COMPILATION_CACHE_DIR=os.path.join(tempfile.gettempdir(), "llrmpp-notebook-xla-cache"),
        JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS="0",
        XLA_FLAGS=QUICK_XLA_FLAGS,
        **env,
    )
    proc = subprocess.run(
        [sys.executable, "-c", runner], cwd=ROOT, env=env, capture_output=True, text=True, timeout=600
    )
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-5000:]
    return proc, json.loads(out.read_text())


@pytest.mark.slow
@pytest.mark.parametrize("name", sorted(NOTEBOOKS))
def test_smoke_run(name, tmp_path):
    label, label_keys, rows = NOTEBOOKS[name]
    saved = tmp_path / "saved"
    proc, data = _run_notebook(name, tmp_path, rows)
    results, labels = data["results"], data["labels"]
    wanted = [int(r) for r in rows.split(",")]
    assert [r["row"] for r in results] == wanted
    lines = proc.stdout.splitlines()
    first = next(i for i, ln in enumerate(lines) if ln.startswith("| "))
    table = [ln for ln in lines[first : first + 3 + len(wanted) + 3] if ln.startswith("| ")][1:]  # minus the header
    table_lines, reference_lines = table[: len(wanted)], table[len(wanted) :]
    runnable = any(r["status"] == "ok" for r in results)
    # the untrained chosen row and the two baselines follow the rows
    assert [ln.split("|")[2].strip() for ln in reference_lines] == (
        ["untrained", "mean colour", "nearest view"] if runnable else []
    )
    for r, line in zip(results, table_lines, strict=True):
        assert {k: r[k] for k in label_keys} == labels[r["row"]]
        cells = [c.strip() for c in line.strip("|").split("|")]
        assert cells[1 : 1 + len(label_keys)] == [r[k] for k in label_keys]
        if r["status"] != "ok":
            assert r["status"].startswith("not run: ") and f"row {r['row']}: not run" in proc.stdout
            continue
        assert f"{r['psnr']:.2f} ± {r['psnr_ci']:.2f}" in cells  # the table shows this row's PSNR and interval
        for k in ("psnr", "ssim", "final_loss", "recon_s", "render_s"):
            assert _finite(r[k]), (k, r[k])
        assert -1.0 <= r["ssim"] <= 1.0 and r["recon_s"] > 0 and r["render_s"] > 0
        assert r["params"] > 0 and r["gaussians"] > 0
        assert r["seeds"] == 2 and len(r["psnr_seeds"]) == 2 and r["psnr_std"] >= 0 and r["psnr_ci"] > 0
        if label == "tb:dep_ab":
            assert _finite(r["abs_diff"]) and 0.0 <= r["delta_1_25"] <= 1.0
    record = json.loads((saved / f"{name}_smoke.json").read_text())
    assert [r["row"] for r in record["results"]] == wanted and record["seeds"] == 2
    assert record["commit"] == "abc1234+dirty"  # the revision the runner passed in
    assert record["wall_s"] > 0 and len(record["orderings"]) == len(data["orderings"])
    assert (saved / f"{name}_smoke.png").stat().st_size > 0
    assert "| paper ordering " in proc.stdout


@pytest.mark.slow
def test_workers_give_the_same_numbers(tmp_path):
    """Trainings on a pool of 2 single-core worker processes (``LLRMPP_NOTEBOOK_WORKERS``)
    score as the same trainings run one after another in the notebook's process (the oracle):
    same seeds, same batches, so equal up to float reassociation (<= 1e-4 dB, 1e-5 relative
    loss). Also checks that the workers do not re-run the notebook script (one table)."""
    runs = {
        w: _run_notebook("table6_partitions", tmp_path / f"w{w}", "0", LLRMPP_NOTEBOOK_WORKERS=str(w)) for w in (1, 2)
    }
    (_, one), (proc, two) = runs[1], runs[2]
    assert proc.stdout.count("| paper ordering ") == 1 and "2 worker(s)" in proc.stdout
    a, b = one["results"][0], two["results"][0]
    assert b["psnr_seeds"] == pytest.approx(a["psnr_seeds"], abs=1e-4)
    assert b["final_loss_seeds"] == pytest.approx(a["final_loss_seeds"], rel=1e-5)
    assert a["psnr_seeds"][0] != a["psnr_seeds"][1]  # the seeds differ, so a mix-up would show


@pytest.fixture
def ablation():
    from llrmpp_jax import ablation

    return ablation


def test_interval_matches_student_t(ablation):
    rng = __import__("numpy").random.default_rng(7)
    x = rng.normal(20.0, 0.3, size=3)
    iv = ablation.interval(x)
    sd = math.sqrt(sum((v - sum(x) / 3) ** 2 for v in x) / 2)
    # t_{0.975, 2 dof} = 4.302652729911275 (statistical tables), independent of scipy
    assert iv["mean"] == pytest.approx(sum(x) / 3, abs=1e-12)
    assert iv["std"] == pytest.approx(sd, rel=1e-12)
    assert iv["ci"] == pytest.approx(4.302652729911275 * sd / math.sqrt(3), rel=1e-9)
    assert math.isnan(ablation.interval([1.0])["ci"])


def test_seeds_to_resolve_is_where_the_interval_first_excludes_zero(ablation):
    # t_{0.995} quantiles from statistical tables (independent of scipy): 4 dof 4.604095,
    # 5 dof 4.032143, 15 dof 2.946713. sd 1: 5 seeds give a 99% half-width of 2.059, 6 seeds 1.646.
    assert 4.604095 / math.sqrt(5) > 1.8 > 4.032143 / math.sqrt(6)
    assert ablation.seeds_to_resolve(1.0, 1.8, 0.99) == 6
    assert ablation.seeds_to_resolve(1.0, -1.8, 0.99) == 6
    assert ablation.seeds_to_resolve(2.0, 3.6, 0.99) == 6
    assert ablation.seeds_to_resolve(1.0, 0.0) is None
    assert ablation.seeds_to_resolve(1.0, 0.01, cap=50) is None
    # About half of the tables with that true difference and spread resolve at that count.
    rng = np.random.default_rng(3)
    n = ablation.seeds_to_resolve(0.4, 0.3, 0.99)
    assert n == 16  # 2.946713 x 0.4 / 4 = 0.295 < 0.3; at 15 seeds 2.976843 x 0.4 / sqrt(15) = 0.307
    d = rng.normal(0.3, 0.4, size=(20000, n))
    half = 2.946713
    resolved = d.mean(1) - half * d.std(1, ddof=1) / math.sqrt(n) > 0
    assert 0.35 < resolved.mean() < 0.65, (n, resolved.mean())


def _row(i: int, psnr_seeds, lpips_seeds, paper_psnr: str, paper_lpips: str, status: str = "ok") -> dict:
    return {
        "row": i,
        "status": status,
        "psnr_seeds": psnr_seeds,
        "lpips_seeds": lpips_seeds,
        "psnr": 0.0,
        "lpips": 0.0,
        "paper": {"PSNR": paper_psnr, "LPIPS": paper_lpips},
    }


def test_compare_verdicts(ablation):
    Od = ablation.Ordering
    results = [
        _row(0, [20.0, 20.5, 21.0], [0.50, 0.40, 0.45], "28.0", "0.10"),
        _row(1, [20.3, 20.9, 21.2], [0.40, 0.30, 0.34], "28.5", "0.08"),  # +0.3/+0.4/+0.2 dB, LPIPS -0.1
        _row(2, [19.0, 21.9, 20.0], [0.5, 0.4, 0.45], "28.9", "0.07"),  # -1/+1.4/-1: straddles 0
        {"row": 3, "status": "not run: no splatter", "paper": {}},
    ]
    got = ablation.compare(
        results,
        [Od("1 > 0", 1, 0), Od("0 > 1", 0, 1), Od("1 > 0 lpips", 1, 0, "lpips"), Od("2 > 0", 2, 0), Od("3 > 0", 3, 0)],
    )
    assert [c["verdict"] for c in got] == ["reproduced", "reversed", "reproduced", "not resolved", "not run"]
    assert got[0]["diff"] == pytest.approx(0.3) and got[0]["paper_diff"] == pytest.approx(0.5)
    assert got[1]["diff"] == pytest.approx(-0.3) and got[0]["diff_ci"] == pytest.approx(got[1]["diff_ci"])
    assert got[2]["diff"] == pytest.approx(0.1037, abs=1e-3) and got[2]["paper_diff"] == pytest.approx(0.02)
    table = ablation.format_orderings(got)
    cells = {ln.split("|")[1].strip(): [c.strip() for c in ln.split("|")[2:-1]] for ln in table.splitlines()[2:-2]}
    assert cells["2 > 0"][:2] == ["psnr", "+0.900"] and cells["2 > 0"][2].startswith("-0.200 ± ")
    assert cells["2 > 0"][3:] == ["3", "not resolved"] and cells["3 > 0"][1:] == ["-", "-", "-", "not run"]
    assert table.splitlines()[-1] == "Intervals: paired differences over seeds, Student-t, 95% two-sided."
    # Rows that ran different numbers of seeds are paired over the seeds both ran.
    results[1] = _row(1, [20.3, 20.9, 21.2, 30.0], [0.40, 0.30, 0.34, 0.1], "28.5", "0.08")
    assert ablation.compare(results, [Od("1 > 0", 1, 0)])[0]["seeds"] == 3
    assert ablation.compare(results, [Od("1 > 0", 1, 0)])[0]["diff"] == pytest.approx(0.3)


def test_sequential_table_adds_seeds_only_where_an_ordering_is_unresolved(ablation, monkeypatch):
    """Rows 1 and 0 differ by 1 dB +- 0.1 (resolved with the first 3 seeds); rows 2 and 0 by
    noise of sd 1 around 0 (never resolved: seeds are added up to the cap); row 3 is in no
    ordering (never more than the first seeds). Trainings are replaced by draws."""
    from llrmpp_jax.ablation import tables

    rng = np.random.default_rng(0)
    calls = []

    def fake_run_seed(cfg, scale, variant, seed, keep_params=False):
        row = cfg.decoder.dim // 8 - 1
        calls.append((row, seed))
        psnr = 20.0 + {0: 0.0, 1: 1.0 + 0.1 * rng.standard_normal(), 2: rng.standard_normal(), 3: 5.0}[row]
        return tables.SeedRun(
            {"psnr": psnr, "eval_dropped": 0}, np.zeros(4, np.float32), 1.0, 0, {} if keep_params else None
        )

    monkeypatch.setattr(tables, "run_seed", fake_run_seed)
    monkeypatch.setattr(tables, "time_model", lambda *a: {})
    monkeypatch.setattr(tables, "references", lambda *a: [])
    monkeypatch.setattr(tables, "_held_out", lambda scale, cfg: [None])
    monkeypatch.delenv("LLRMPP_NOTEBOOK_ROWS", raising=False)
    scale = dataclasses.replace(ablation.make_scale("smoke", paper_views=4), seeds=3, max_seeds=6, workers=1)
    V, Od = ablation.Variant, ablation.Ordering
    variants = [
        V({"x": str(i)}, lambda base, i=i: replace(base, decoder=replace(base.decoder, dim=8 * (i + 1))), {})
        for i in range(4)
    ]
    orderings = [Od("1 > 0", 1, 0), Od("2 > 0", 2, 0)]
    monkeypatch.setattr(tables, "count_params", lambda p: 0)
    run = ablation.run_table(variants, scale, orderings)
    seeds = {r["row"]: r["seeds"] for r in run.results}
    assert seeds == {0: 6, 1: 3, 2: 6, 3: 3}
    assert sorted(calls) == sorted({(row, s) for row, n in seeds.items() for s in range(n)})  # each once
    by = {c["ordering"]: c for c in run.comparisons}
    assert by["1 > 0"]["verdict"] == "reproduced" and by["1 > 0"]["stopped"] == "resolved at 3 seeds"
    assert by["1 > 0"]["confidence"] == 0.99
    assert by["2 > 0"]["seeds"] == 6 and by["2 > 0"]["stopped"] == "the cap of 6 seeds"
    assert "3-6 seeds per row" in ablation.format_run(run, ["x"])
    # Out of time after the first round: no seed is added, and the reason is given.
    calls.clear()
    run = ablation.run_table(variants, dataclasses.replace(scale, budget_min=0.0), orderings)
    assert len(calls) == 12 and {c["stopped"] for c in run.comparisons} == {
        "resolved at 3 seeds",
        "the 0-minute budget, at 3 seeds",
    }


@pytest.mark.parametrize(
    "env, value, message",
    [
        ("LLRMPP_NOTEBOOK_SCALE", "huge", "LLRMPP_NOTEBOOK_SCALE='huge': expected one of smoke, cpu, paper"),
        ("LLRMPP_NOTEBOOK_SEEDS", "0", "LLRMPP_NOTEBOOK_SEEDS='0': expected an integer >= 1, got 0"),
        ("LLRMPP_NOTEBOOK_SEEDS", "three", "LLRMPP_NOTEBOOK_SEEDS='three': expected an integer >= 1"),
        ("LLRMPP_NOTEBOOK_STEPS", "-5", "LLRMPP_NOTEBOOK_STEPS='-5': expected an integer >= 0, got -5"),
        ("LLRMPP_NOTEBOOK_WORKERS", "0", "LLRMPP_NOTEBOOK_WORKERS='0': expected an integer >= 1, got 0"),
    ],
)
def test_bad_environment_is_one_line(ablation, monkeypatch, env, value, message):
    monkeypatch.setenv(env, value)
    with pytest.raises(ValueError) as err:
        ablation.make_scale(ablation.scale_name(), paper_views=4)
    assert str(err.value) == message


@pytest.mark.parametrize(
    "rows, message",
    [
        ("0,9", "LLRMPP_NOTEBOOK_ROWS='0,9': rows [9] outside 0..2"),
        ("1;2", "LLRMPP_NOTEBOOK_ROWS='1;2': expected comma-separated row indices or 'none'"),
    ],
)
def test_bad_rows_are_one_line(ablation, monkeypatch, rows, message):
    monkeypatch.setenv("LLRMPP_NOTEBOOK_ROWS", rows)
    variants = [ablation.Variant({"x": str(i)}, None, {}) for i in range(3)]
    with pytest.raises(ValueError) as err:
        ablation.selected(variants)
    assert str(err.value) == message


@pytest.mark.parametrize("echo", [False, True])
def test_progress_is_echoed_to_the_terminal_only_when_asked(ablation, monkeypatch, echo):
    """In a kernel (sys.stderr is not the process's own), a progress line goes to the notebook
    once, and to the terminal only under notebooks/_execute.py (LLRMPP_NOTEBOOK_ECHO)."""
    import io

    notebook, kernel_stderr, terminal = io.StringIO(), io.StringIO(), io.StringIO()
    monkeypatch.setattr(sys, "stdout", notebook)
    monkeypatch.setattr(sys, "stderr", kernel_stderr)
    monkeypatch.setattr(sys, "__stderr__", terminal)
    if echo:
        monkeypatch.setenv("LLRMPP_NOTEBOOK_ECHO", "1")
    else:
        monkeypatch.delenv("LLRMPP_NOTEBOOK_ECHO", raising=False)
    ablation.progress("row 0 seed 1: PSNR 19.00")
    assert notebook.getvalue() == "row 0 seed 1: PSNR 19.00\n" and kernel_stderr.getvalue() == ""
    assert terminal.getvalue() == ("row 0 seed 1: PSNR 19.00\n" if echo else "")


def test_cpu_scale_is_the_pilots(ablation, monkeypatch):
    """The cpu scale: the demo model with the paper's chosen head and decoder, 3 seeds, and the
    step budget the pilot recorded in experiments/results/ablations/pilot_cpu.json."""
    for env in ("LLRMPP_NOTEBOOK_STEPS", "LLRMPP_NOTEBOOK_SEEDS", "LLRMPP_NOTEBOOK_WORKERS"):
        monkeypatch.delenv(env, raising=False)
    scale = ablation.make_scale("cpu", paper_views=8, depth=True)
    assert scale.seeds == 3 and scale.size == 64 and scale.base.outputs == ("rgb", "depth")
    assert (scale.lr, scale.warmup) == (1e-3, 50)  # the stalled-seed fix (notebooks/README.md)
    assert (scale.base.head.gaussians_per_token, scale.base.head.feature_dim) == (16, 32)
    assert (scale.base.decoder.blocks, scale.base.decoder.dim, scale.base.decoder.partitions) == ("LLGGG", 64, 2)
    # the splat buffer can hold every (Gaussian, tile) pair of a full-size render: no overflow
    n = 4 * 64 * 64  # colour mode: one Gaussian per input pixel
    assert scale.base.splat.capacity(n, 64, 64) == n * 16
    pilot = json.load(open(os.path.join(ROOT, "experiments", "results", "ablations", "pilot_cpu.json")))
    assert scale.steps in pilot["budgets"]
    assert ablation.make_scale("cpu", paper_views=8, cpu_seeds=5).seeds == 5
    with pytest.raises(ValueError, match=r"^make_scale: cpu_seeds must be >= 1, got 0$"):
        ablation.make_scale("cpu", paper_views=8, cpu_seeds=0)
    assert ablation.make_scale("cpu", paper_views=8, cpu_steps=1000).steps == 1000
    assert ablation.make_scale("cpu", paper_views=8).steps == ablation.CPU_STEPS
    assert ablation.make_scale("smoke", paper_views=8, cpu_steps=1000).steps == 40  # the cpu scale's only
    with pytest.raises(ValueError, match=r"^make_scale: cpu_steps must be >= 1, got 0$"):
        ablation.make_scale("cpu", paper_views=8, cpu_steps=0)


def test_procedural_tables_keep_world_units_and_reach_their_depths(ablation):
    """Every table at the smoke and cpu scales keeps world units (no per-window rescaling)
    and its Gaussians reach PROCEDURAL_MAX_DIST along a ray, beyond 99% of the target pixels'
    ray distances in freshly drawn cpu-scale training windows (the oracle: ray-cast
    procedural depth, 64 batches, at 32x32 for speed: depth does not depend on the
    resolution); the depth tables start the head at PROCEDURAL_DEPTH_BIAS, within 0.15 (log
    units) of those windows' log geometric-mean depth. The paper scale keeps Long-LRM's
    rescaling and its config's own bias and range."""
    import numpy as np

    from llrmpp_jax import config as C
    from llrmpp_jax.data import BatchConfig, BatchIterator, ProceduralConfig, ProceduralSource
    from llrmpp_jax.geometry import unproject_depth

    for name in ("smoke", "cpu"):
        rgb, depth = (ablation.make_scale(name, paper_views=8, depth=d) for d in (False, True))
        for scale in (rgb, depth):
            assert scale.base.head.max_dist == ablation.PROCEDURAL_MAX_DIST and not scale.rescale
        assert depth.base.decoder.depth_bias == ablation.PROCEDURAL_DEPTH_BIAS
        assert rgb.base.decoder.depth_bias == C.DecoderConfig().depth_bias
    for depth in (False, True):
        paper = ablation.make_scale("paper", paper_views=8, depth=depth)
        preset = C.paper_scannet() if depth else C.paper_dl3dv()
        assert paper.base.decoder.depth_bias == preset.decoder.depth_bias and paper.rescale
        assert paper.base.head.max_dist == C.GaussianHeadConfig().max_dist
    scale = ablation.make_scale("cpu", paper_views=4, depth=True)
    source = ProceduralSource(
        ProceduralConfig(height=32, width=32, num_frames=scale.frames), size=ablation.TRAIN_SCENES
    )
    cfg = BatchConfig(
        global_batch=scale.batch,
        num_inputs=scale.num_inputs,
        num_targets=scale.num_targets,
        with_depth=True,
        min_span=scale.min_span,
        max_span=scale.max_span,
        rescale=scale.rescale,
    )
    logs, ray_distances = [], []
    with BatchIterator(source, cfg, seed=123, num_devices=1) as batches:
        for _ in range(64):
            batch = next(batches)
            depth, c2w = batch["target_depth"], batch["target_c2w"]
            points = unproject_depth(depth, c2w, batch["target_intrinsics"])
            distance = np.linalg.norm(points - c2w[..., None, None, :3, 3], axis=-1)  # along the ray
            logs.append(np.log(depth[depth > 0]))
            ray_distances.append(distance[depth > 0])
    assert abs(float(np.mean(np.concatenate(logs))) - ablation.PROCEDURAL_DEPTH_BIAS) < 0.15
    assert np.percentile(np.concatenate(ray_distances), 99) < ablation.PROCEDURAL_MAX_DIST


def test_rows_are_scored_on_the_ablations_held_out_views(ablation):
    """A row's held-out samples (``llrmpp train``'s eval_samples of its experiment) are the
    ablations' own: procedural scenes of seed EVAL_SEED + i in world units, the paper's split
    at the smoke scale (every 8th frame a target, k-means inputs) and at the cpu scale one
    draw of the training view sampler from the generator of entropy (7, i) in 8-frame
    windows, the same for every training seed. The oracle builds them from the scene and
    the selection functions."""
    import numpy as np

    from llrmpp_jax.data import (
        ProceduralConfig,
        ViewGeometry,
        eval_views,
        make_sample,
        procedural_scene,
        training_views,
    )

    for name in ("smoke", "cpu"):
        scale = dataclasses.replace(ablation.make_scale(name, paper_views=4, depth=True), eval_scenes=2)
        samples = ablation.held_out_samples(scale.base, scale)
        assert len(samples) == 2
        proc = ProceduralConfig(height=scale.size, width=scale.size, num_frames=scale.frames)
        for i, s in enumerate(samples):
            scene = procedural_scene(ablation.EVAL_SEED + i, proc)
            if name == "smoke":
                inputs, targets = eval_views(scene.c2w, scale.num_inputs)
            else:
                inputs, targets = training_views(
                    np.random.default_rng([7, i]),
                    len(scene),
                    scale.num_inputs,
                    scale.num_targets,
                    8,
                    8,
                    input_weight=0.0,
                )
            want = make_sample(scene, inputs, targets, ViewGeometry(), with_depth=True, rescale=False)
            assert set(s) == set(want)
            for k in want:
                np.testing.assert_array_equal(s[k], want[k], err_msg=f"{name} {k}")


def test_summary_lists_every_table_and_ordering(tmp_path, monkeypatch):
    """``notebooks/_summary.py``: one line per ordering of an executed table, with the
    numbers of its JSON record; every other table is listed as not executed."""
    monkeypatch.syspath_prepend(NB_DIR)
    import _summary  # pyright: ignore[reportMissingImports] -- notebooks/ is put on sys.path by the monkeypatch above

    record = {
        "wall_s": 1926.0,
        "seeds": 3,
        "steps": 400,
        "commit": "abc1234",
        "orderings": [
            {
                "ordering": "S=2 > S=1 (PSNR)",
                "metric": "psnr",
                "diff": 0.9582,
                "diff_ci": 1.9061,
                "paper_diff": 0.99,
                "verdict": "not resolved",
            },
            {"ordering": "x > y", "metric": "lpips", "verdict": "not run"},
        ],
        "results": [
            _row(0, [20.0, 20.5, 21.0], [0.5] * 3, "28.0", "0.1"),
            _row(1, [20.3, 20.6, 21.4], [0.4] * 3, "29.0", "0.1"),
        ],
    }
    (tmp_path / "table6_partitions_cpu.json").write_text(json.dumps(record))
    lines = _summary.summary("cpu", str(tmp_path)).splitlines()
    assert "- `table6_partitions`: 32.1 min, 3 seeds x 400 steps, commit abc1234" in lines
    assert {ln for ln in lines if "not executed at" in ln} == {
        f"- `{n}`: not executed at the cpu scale" for n in NOTEBOOKS if n != "table6_partitions"
    }
    assert "| 6 | S=2 > S=1 (PSNR) | psnr | +0.990 | +0.958 ± 1.906 | 95% | 3 | not resolved |" in lines
    assert "| 6 | x > y | lpips | - | - | 95% | 3 | not run |" in lines
    # The central claims: Table 6's from its rows' seeds (diffs 0.3, 0.1, 0.4: mean 0.267, sd
    # 0.153; 95% half-width 4.303 x 0.153 / sqrt(3) = 0.379); the others not executed.
    assert "| 6 | S=2 > S=1 | +1.000 | +0.267 ± 0.379 | 95% | 3 | not resolved | 0.153 | 3 | 4 |" in lines
    assert "| 5 | feature (LLGGG) > colour | | | | | not executed | | | |" in lines
    # A sequential table: its level, each ordering's seeds and what stopped it.
    record["orderings"][0].update(confidence=0.99, seeds=7, stopped="10 seeds")
    (tmp_path / "table6_partitions_cpu.json").write_text(json.dumps(record))
    lines = _summary.summary("cpu", str(tmp_path)).splitlines()
    assert "- `table6_partitions`: 32.1 min, 3 to 7 seeds (sequential) x 400 steps, commit abc1234" in lines
    assert (
        "| 6 | S=2 > S=1 (PSNR) | psnr | +0.990 | +0.958 ± 1.906 | 99% | 7 | not resolved, stopped by 10 seeds |"
        in lines
    )


def test_table_reports_splat_overflow(ablation):
    """A row whose splat buffer overflowed gets a note with the dropped intersections per
    training step and per held-out scene; a row without overflow gets none."""
    scale = ablation.make_scale("smoke", paper_views=4)  # 40 steps, 4 held-out scenes
    rows = [
        {
            "row": 0,
            "x": "a",
            "chosen": False,
            "paper": {},
            "status": "ok",
            "train_dropped": 8000.0,
            "eval_dropped": 8.0,
        },
        {"row": 1, "x": "b", "chosen": True, "paper": {}, "status": "ok", "train_dropped": 0.0, "eval_dropped": 0.0},
    ]
    text = ablation.format_run(ablation.TableRun(scale, rows, [], {}, 60.0), ["x"])
    assert (
        "row 0: the splat buffer overflowed: 200 intersections dropped per training step, "
        "2 per held-out scene (mean over seeds)"
    ) in text.splitlines()
    assert "row 1:" not in text

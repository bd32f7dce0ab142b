"""Command line and training loop: experiment files, one-line errors, train -> resume -> eval."""

import glob
import json
import os
import shutil
import subprocess
import sys
from dataclasses import replace

import numpy as np
import pytest

from llrmpp_jax.cli import main
from llrmpp_jax.experiment import DataConfig, load_experiment
from tests.helpers.environment import ROOT
from tests.helpers.micro_experiment import micro_experiment


def _is_experiment(path: str) -> bool:
    """An experiment file defines ``get_config``; the others (bench_*, ship_weights, ...) are scripts."""
    with open(path) as f:
        return "\ndef get_config(" in f.read()


# The recipes in the package and the experiment files kept in experiments/.
EXPERIMENT_FILES = sorted(
    p
    for d in ("llrmpp_jax/recipes", "experiments")
    for p in glob.glob(os.path.join(ROOT, d, "*.py"))
    if _is_experiment(p)
)


@pytest.mark.parametrize("path", EXPERIMENT_FILES, ids=os.path.basename)
def test_experiment_files_load(path):
    exp = load_experiment(path)
    assert exp.stages and all(s.steps > 0 for s in exp.stages)
    with open(path) as f:
        assert "llrmpp " in f.read().split('"""')[1], "the header must give the run command"


def test_paper_stage_tables():
    """Tables 8 and 9 of the paper, written out by hand."""
    dl3dv = load_experiment("dl3dv")
    got = [(s.num_inputs, s.num_targets, s.resize_h, s.steps, s.global_batch) for s in dl3dv.stages]
    assert got == [(8, 8, 256, 60_000, 256), (8, 8, 512, 10_000, 64), (8, 8, 540, 10_000, 64), (32, 8, 540, 10_000, 64)]
    scannet = load_experiment("scannet")
    got = [(s.num_inputs, s.resize_h, s.resize_w, s.steps, s.global_batch) for s in scannet.stages]
    assert got == [(8, 256, None, 20_000, 128), (8, 336, 448, 5_000, 128), (128, 336, 448, 2_000, 64)]
    assert scannet.model.outputs == ("rgb", "depth")


def test_no_function_in_cli_is_over_60_lines():
    """Each ``llrmpp`` verb is a short command plus a short options function (``llrmpp_jax/cli.py``'s
    docstring): a function of ``cli.py`` over 60 lines, decorators and docstring included, is a
    verb that needs splitting."""
    import ast

    import llrmpp_jax.cli as cli

    with open(cli.__file__) as f:
        tree = ast.parse(f.read())
    long = [
        (node.name, node.lineno, node.end_lineno - min([node.lineno, *(d.lineno for d in node.decorator_list)]) + 1)  # pyright: ignore[reportOptionalOperand] -- parsed functions have end_lineno
        for node in ast.walk(tree)
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef))
    ]
    assert long and not [row for row in long if row[2] > 60], [row for row in long if row[2] > 60]


def test_the_parser_s_verbs_are_the_registry_s():
    """``build_parser`` adds exactly the verbs of ``cli.VERBS``, in their order (``llrmpp --help``'s),
    each running its registered command, so a new verb is one entry there."""
    import argparse

    from llrmpp_jax.cli import VERBS, build_parser

    parser = build_parser()
    (verbs,) = (a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    assert list(verbs.choices) == [v.name for v in VERBS] and len(VERBS) == len({v.name for v in VERBS})
    assert [c.help for c in verbs._choices_actions] == [v.help for v in VERBS]
    for verb in VERBS:
        assert verbs.choices[verb.name].get_default("fn") is verb.command, verb.name


def _run_cli(*args) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "llrmpp_jax.cli", *args], capture_output=True, text=True, timeout=300, cwd=ROOT
    )


@pytest.mark.parametrize(
    "args, message",
    [
        (["train", "--config", "no/such/file.py", "--workdir", "/tmp/x"], "config file not found"),
        (
            ["eval", "--config", "demo", "--checkpoint", "/no/such/dir", "--out", "/tmp/x"],
            "checkpoint folder not found",
        ),
        (["eval", "--config", "demo", "--checkpoint", "pretrained:nope", "--out", "/tmp/x"], "no shipped model 'nope'"),
        (
            ["render", "--config", "demo", "--checkpoint", "/tmp", "--scene", "/no/scene", "--out", "/tmp/x"],
            "scene not found",
        ),
        (["convert", "--checkpoint", "/no/such.pt", "--out", "/tmp/x"], "checkpoint file not found"),
        (
            ["train", "--config", "demo", "--workdir", "/tmp/x", "--init", "/no/such/dir"],
            "--init: checkpoint folder not found",
        ),
        (
            ["train", "--config", "dl3dv", "--workdir", "/tmp/x"],
            "uses Long-LRM's VGG19 perceptual loss and needs its weights",
        ),
        (
            ["train", "--config", "scannet", "--workdir", "/tmp/x", "--vgg16"],
            "dataset path does not exist",
        ),  # VGG16 opted into: the next check speaks
    ],
)
def test_bad_input_is_one_clear_line(args, message):
    res = _run_cli(*args)
    assert res.returncode == 2
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("llrmpp: error:") and message in lines[0], res.stderr


def _bad_files(tmp_path) -> list[tuple[list[str], str]]:
    """Files that are not what they claim, each with the command that reads it and the start
    of the one line it must give."""
    from tests.helpers.environment import shared_path

    golden = shared_path("golden", "long_lrm_tiny", "state_dict.npz")
    data = open(golden, "rb").read()
    npz_as_pt = tmp_path / "other_model.pt"  # an .npz of another (the tiny) model
    npz_as_pt.write_bytes(data)
    (tmp_path / "cut.npz").write_bytes(data[: len(data) // 3])
    (tmp_path / "cut.pt").write_bytes(data[: len(data) // 3])
    subprocess.run(
        [
            sys.executable,
            "-c",
            "import torch\nclass Cfg: pass\n"
            f"torch.save({{'model': {{'a': torch.ones(2)}}, 'cfg': Cfg()}}, {str(tmp_path / 'objects.pt')!r})",
        ],
        check=True,
    )
    (tmp_path / "broken.py").write_text("def get_config(:\n    pass\n")
    out = str(tmp_path / "out")
    return [
        (["convert", "--checkpoint", str(npz_as_pt), "--out", out], f"cannot convert {npz_as_pt}: "),
        (
            ["convert", "--checkpoint", str(tmp_path / "cut.npz"), "--out", out],
            f"{tmp_path / 'cut.npz'}: not a .npz archive (not a zip file",
        ),
        (
            ["convert", "--checkpoint", str(tmp_path / "cut.pt"), "--out", out],
            f"{tmp_path / 'cut.pt'}: not a readable torch checkpoint or .npz archive",
        ),
        (
            ["convert", "--checkpoint", str(tmp_path / "objects.pt"), "--out", out],
            f"{tmp_path / 'objects.pt'}: holds Python objects other than tensors",
        ),
        (
            ["train", "--config", str(tmp_path / "broken.py"), "--workdir", out],
            f"{tmp_path / 'broken.py'}:1: syntax error in the experiment file",
        ),
    ]


def test_files_that_are_not_what_they_claim_are_one_line(tmp_path):
    """A renamed archive of another model, truncated archives, a pickle of Python objects, an
    experiment file with a syntax error: exit 2, one line naming the file, no traceback."""
    for args, start in _bad_files(tmp_path):
        res = _run_cli(*args)
        lines = res.stderr.strip().splitlines()
        assert res.returncode == 2 and len(lines) == 1, (args, res.stderr)
        assert lines[0].startswith(f"llrmpp: error: {start}"), (args, lines[0])
        assert len(lines[0]) < 600  # a long list is cut to its first entries and a count
    assert not os.path.exists(tmp_path / "out")  # nothing half-written


def test_an_empty_checkpoint_folder_is_one_line_and_nothing_after(tmp_path):
    """orbax's start-up clean-up thread is joined, so no traceback follows the error at exit."""
    res = _run_cli("eval", "--config", "demo", "--checkpoint", str(tmp_path), "--out", str(tmp_path / "ev"))
    assert res.returncode == 2
    assert res.stderr.strip().splitlines() == [
        f"llrmpp: error: no checkpoint in {tmp_path} (expected a params folder or a training workdir)"
    ]


def test_wrong_vgg19_file_is_one_line_naming_the_first_mismatching_key(tmp_path):
    """A VGG16 state_dict (here its first 8 convolutions) given as VGG19: VGG19 has conv3_4
    at index 16, where VGG16 has a pooling layer."""
    import torch

    sd, idx, cin = {}, 0, 3
    for v in [64, 64, "M", 128, 128, "M", 256, 256, 256, "M", 512, 512]:
        if v == "M":
            idx += 1
            continue
        sd[f"features.{idx}.weight"], sd[f"features.{idx}.bias"] = torch.zeros(v, cin, 3, 3), torch.zeros(v)
        idx, cin = idx + 2, v
    path = str(tmp_path / "vgg16.pth")
    torch.save(sd, path)
    res = _run_cli("convert", "--vgg19", path, "--out", str(tmp_path / "out"))
    assert res.returncode == 2
    lines = res.stderr.strip().splitlines()
    assert (
        len(lines) == 1 and "first mismatching key 'features.16.weight': missing (vgg19 has conv3_4 there)" in lines[0]
    ), res.stderr
    assert not os.path.exists(tmp_path / "out")


def test_bad_dataset_and_batch_fail_before_compiling(tmp_path):
    exp = micro_experiment()
    bad = replace(exp, data=DataConfig(kind="colmap", path=str(tmp_path / "missing")))
    from llrmpp_jax.trainer import train

    with pytest.raises(FileNotFoundError, match="dataset path does not exist"):
        train(bad, str(tmp_path / "w"))
    odd = replace(exp, stages=(replace(exp.stages[0], global_batch=3),))
    with pytest.raises(ValueError, match="global_batch=3 does not split over 2 devices"):
        train(odd, str(tmp_path / "w"))


def _micro_experiment_file(tmp_path, steps: int):
    """An experiment file (for ``--config``) whose ``get_config`` is ``micro_experiment(steps)``."""
    path = tmp_path / "micro.py"
    path.write_text(
        f"import sys\nsys.path.insert(0, {ROOT!r})\nfrom tests.helpers.micro_experiment import micro_experiment\n"
        f"def get_config():\n    return micro_experiment({steps:d})\n"
    )
    return path


def test_train_resume_and_eval(tmp_path, capsys):
    """2 steps, then the same run extended to 3 resumes at step 2; eval reads the checkpoint,
    with ``--refine-steps`` adds a refined row per scene, and rejects a negative count or
    perceptual weight in one line."""
    from llrmpp_jax.trainer import train

    work = str(tmp_path / "run")
    first = train(micro_experiment(2), work, progress=False)
    assert first["stages"][0]["steps"] == 2
    log = json.load(open(os.path.join(work, "train_log.json")))
    assert [h["step"] for h in log["history"]] == [1, 2]
    assert all(h["loss"] > 0 and h["skipped_total"] == h["skipped_grad_norm_total"] == 0 for h in log["history"])
    second = train(micro_experiment(3), work, progress=False)
    assert [h["step"] for h in second["history"]] == [3]  # resumed, not restarted
    assert os.listdir(os.path.join(work, "tb"))
    cfg_file = _micro_experiment_file(tmp_path, 3)
    assert main(["eval", "--config", str(cfg_file), "--checkpoint", work, "--out", str(tmp_path / "ev")]) == 0
    rows = open(tmp_path / "ev" / "per_scene.csv").read().splitlines()
    assert rows[0].startswith("scene,method,psnr,ssim,lpips") and len(rows) == 1 + 3
    assert (
        main(
            [
                "eval",
                "--config",
                str(cfg_file),
                "--checkpoint",
                work,
                "--refine-steps",
                "2",
                "--out",
                str(tmp_path / "ev2"),
            ]
        )
        == 0
    )
    rows = open(tmp_path / "ev2" / "per_scene.csv").read().splitlines()
    assert [r.split(",")[1] for r in rows[1:]] == ["model", "refined_2", "mean_colour", "nearest_view"]
    assert "refined_2" in json.load(open(tmp_path / "ev2" / "metrics.json"))
    # a negative --refine-steps or perceptual weight: the parser's (tests/test_bad_inputs.py)
    capsys.readouterr()
    n_in = micro_experiment(3).stages[-1].num_inputs
    assert (
        main(
            [
                "eval",
                "--config",
                str(cfg_file),
                "--checkpoint",
                work,
                "--refine-steps",
                "2",
                "--refine-views-per-step",
                str(n_in + 1),
                "--out",
                str(tmp_path / "ev3"),
            ]
        )
        == 2
    )
    assert capsys.readouterr().err.strip().splitlines() == [
        f"llrmpp: error: --refine-views-per-step must be in [1, {n_in}] (the input views), got {n_in + 1}"
    ]
    assert not os.path.exists(tmp_path / "ev3")


def test_sigterm_stops_train_with_a_checkpoint(tmp_path):
    """``llrmpp train`` gets SIGTERM during a 1,000-step run: it stops after the current step
    with a verified checkpoint of that step, exits 128 + 15, records the signal in
    train_log.json, skips the final evaluation and puts the old handler back (resuming from
    a checkpoint: test_train_resume_and_eval)."""
    import signal
    import threading

    from llrmpp_jax.train import verify_checkpoint

    before = signal.getsignal(signal.SIGTERM)

    def send_once_installed():  # the signal goes out only once training handles it
        for _ in range(12_000):
            if signal.getsignal(signal.SIGTERM) is not before:
                os.kill(os.getpid(), signal.SIGTERM)
                return
            threading.Event().wait(0.01)

    cfg_file = _micro_experiment_file(tmp_path, 1000)
    work = str(tmp_path / "run")
    threading.Thread(target=send_once_installed, daemon=True).start()
    assert main(["train", "--config", str(cfg_file), "--workdir", work]) == 128 + signal.SIGTERM.value
    log = json.load(open(os.path.join(work, "train_log.json")))
    stopped_at = log["stages"][0]["steps"]
    assert log["stopped_by"] == "SIGTERM" and 1 <= stopped_at < 1000 and log["evals"] == []
    verify_checkpoint(os.path.join(work, "checkpoints", "s1"), stopped_at)
    assert signal.getsignal(signal.SIGTERM) is before


@pytest.mark.slow
def test_workdir_reconstruct_render_export_feature_mode(tmp_path):
    """A training workdir records its experiment: reconstruct, render and export read it
    with no --config (feature mode: the decoder renders, the PLY carries features and
    partition logits)."""
    from llrmpp_jax.capture import load_gs
    from llrmpp_jax.data import in_memory_scene
    from llrmpp_jax.data.formats import write_nerfstudio_scene
    from llrmpp_jax.export_ply import read_ply
    from llrmpp_jax.params_io import load_params
    from llrmpp_jax.trainer import train

    exp = micro_experiment(1)
    work = str(tmp_path / "run")
    train(exp, work, progress=False)
    _, cfg = load_params(work)
    assert cfg == exp.model
    rng = np.random.default_rng(3)
    c2w = np.tile(np.eye(4), (9, 1, 1))
    c2w[:, 0, 3] = np.linspace(-1.0, 1.0, 9)
    scene = in_memory_scene("s", rng.uniform(0.2, 0.8, (9, 32, 32, 3)), c2w, np.tile([[30.0, 30, 16, 16]], (9, 1)))
    write_nerfstudio_scene(scene, str(tmp_path / "ns"), bits=8)
    gs = str(tmp_path / "s.gs")
    assert (
        main(
            [
                "reconstruct",
                "--checkpoint",
                work,
                "--scene",
                str(tmp_path / "ns"),
                "--num-inputs",
                "2",
                "--size",
                "32",
                "--repeats",
                "1",
                "--out",
                gs,
            ]
        )
        == 0
    )
    assert load_gs(gs).model == exp.model
    assert main(["render", "--gaussians", gs, "--path", "targets", "--quiet", "--out", str(tmp_path / "f")]) == 2
    assert (
        main(
            [
                "render",
                "--gaussians",
                gs,
                "--checkpoint",
                work,
                "--path",
                "orbit",
                "--frames",
                "3",
                "--quiet",
                "--out",
                str(tmp_path / "f"),
            ]
        )
        == 0
    )
    assert sorted(os.listdir(tmp_path / "f")) == ["orbit_00000.png", "orbit_00001.png", "orbit_00002.png"]
    assert main(["export", "--gaussians", gs, "--checkpoint", work, "--ply", str(tmp_path / "s.ply")]) == 0
    back = read_ply(str(tmp_path / "s.ply"))
    assert back.mode == "feature" and back.partition_logits.shape[1] == exp.model.decoder.partitions  # pyright: ignore[reportOptionalMemberAccess] -- a feature-mode PLY has partition logits


def test_train_data_reads_any_capture_through_read_scene():
    """``train --data PATH --format auto``: the trainer's scenes come from read_scene, so a
    COLMAP folder and a nerfstudio folder both load (the old COLMAP image_dir crash)."""
    from llrmpp_jax.experiment_data import scene_source
    from tests.helpers.environment import shared_path

    for name, frames in (("beer", 71), ("fox", 50)):
        data = DataConfig(kind="auto", path=shared_path("data", name))
        source = scene_source(data, held_out=True)
        assert len(source) == 1 and len(source.load(0)) == frames
        # training: less the evaluation's targets, every 8th frame
        assert len(scene_source(data).load(0)) == frames - len(range(0, frames, 8))


def test_evaluation_on_the_training_scenes_is_flagged(tmp_path):
    """``train --data`` evaluates on the training captures: flagged. Procedural evaluation
    (disjoint seeds) and real data with another ``eval_path`` are not."""
    same = str(tmp_path / "caps")
    assert DataConfig(kind="auto", path=same).eval_reads_training_scenes
    assert DataConfig(kind="auto", path=same, eval_path=same + "/").eval_reads_training_scenes
    assert not DataConfig(kind="auto", path=same, eval_path=str(tmp_path / "test")).eval_reads_training_scenes
    assert not DataConfig().eval_reads_training_scenes


def test_training_on_the_evaluated_capture_leaves_out_its_target_frames():
    """``train --data beer``: the evaluation targets every 8th of beer's 71 frames; the
    training scene holds the other 62, camera for camera, and none of the targets."""
    from llrmpp_jax.data.formats import read_scene
    from llrmpp_jax.experiment_data import eval_samples, scene_source
    from tests.helpers.environment import shared_path

    data = DataConfig(kind="auto", path=shared_path("data", "beer"), num_eval_scenes=1)
    full = read_scene(data.path, "auto")  # pyright: ignore[reportArgumentType] -- the config above sets path
    trained = scene_source(data).load(0)
    targets = [i for i in range(len(full)) if i % 8 == 0]
    assert len(full) == 71 and len(trained) == 71 - len(targets) == 62
    np.testing.assert_array_equal(trained.c2w, np.delete(full.c2w, targets, axis=0))
    exp = micro_experiment()
    exp = replace(exp, data=data, stages=(replace(exp.stages[0], num_inputs=8),))
    held_out, _ = eval_samples(exp, exp.stages[0])
    for t in held_out[0]["target_c2w"]:  # every evaluated camera is absent from training
        assert not any(np.allclose(t, c, atol=1e-5) for c in trained.c2w)


def test_eval_on_a_capture_says_and_takes_the_view_size(tmp_path, capsys):
    """``eval --data beer`` (portrait 720x1280) with the micro experiment (square crop, patch 8)
    and ``--size 48x40`` resizes to 48 x 40 before the crop and says so: views 40 x 40 (the
    config's height 32 would give 32 x 16, cropped to 16 x 16). A bad size is one line."""
    import jax

    from llrmpp_jax.model import init_params
    from llrmpp_jax.params_io import save_params
    from tests.helpers.environment import shared_path

    exp = micro_experiment()
    save_params(str(tmp_path / "p"), init_params(jax.random.key(3), exp.model, 2, 32, 32), exp.model)
    cfg_file = _micro_experiment_file(tmp_path, 2)
    base = [
        "eval",
        "--config",
        str(cfg_file),
        "--checkpoint",
        str(tmp_path / "p"),
        "--data",
        shared_path("data", "beer"),
        "--num-inputs",
        "2",
    ]
    capsys.readouterr()
    assert main([*base, "--size", "48x40", "--out", str(tmp_path / "ev")]) == 0
    line = [x for x in capsys.readouterr().out.splitlines() if x.startswith("eval scene beer:")]
    assert line and line[0].startswith("eval scene beer: 2 inputs, 9 targets, views 40x40 (HxW); "), line
    rows = open(tmp_path / "ev" / "per_scene.csv").read().splitlines()
    assert [r.split(",")[1] for r in rows[1:]] == ["model", "mean_colour", "nearest_view"]


def test_eval_takes_a_split_and_says_which(tmp_path, capsys, monkeypatch):
    """``eval --split``: the scannet recipe evaluates the test split by default (its list is
    looked for first, before any weights load); a split name not in train/val/test, a list
    naming a room not on disk, and ``--split`` with ``--data`` are one line each. On a fake
    ScanNet export, ``--split val`` evaluates the val list's room and the output names the split."""
    import jax

    from llrmpp_jax.model import init_params
    from llrmpp_jax.params_io import save_params
    from tests.helpers.fake_scannet import fake_scannet
    from tests.helpers.typechecks import unchecked

    out = ["--out", str(tmp_path / "ev")]
    monkeypatch.chdir(tmp_path)  # the recipe's data/scannet/... paths are relative: absent here
    cases = [
        (
            ["--config", "scannet", "--checkpoint", "pretrained:small", "--split", "dev"],
            "the split must be 'train', 'val' or 'test', got 'dev'",
        ),
        (
            ["--config", "scannet", "--checkpoint", "pretrained:small"],
            "scene list not found: data/scannet/scannetv2_test.txt",
        ),
        (
            ["--config", "scannet", "--checkpoint", "pretrained:small", "--data", str(tmp_path), "--split", "val"],
            "--split picks a split of the config's held-out data; --data names the scenes itself",
        ),
    ]
    root = fake_scannet(
        tmp_path / "scannet", size=32, lists={"val": ["scene0011_00"], "test": ["scene0707_00", "scene0710_00"]}
    )
    cfg_file = tmp_path / "micro_scannet.py"
    cfg_file.write_text(
        f"import dataclasses, sys\nsys.path.insert(0, {ROOT!r})\n"
        "from tests.helpers.fake_scannet import split_data\n"
        "from tests.helpers.micro_experiment import micro_experiment\n"
        "def get_config():\n    exp = micro_experiment(1)\n"
        f"    data = dataclasses.replace(split_data({root!r}, 'test'), eval_inputs='uniform', workers=1)\n"
        "    return dataclasses.replace(exp, data=data)\n"
    )
    cases.append(
        (
            ["--config", str(cfg_file), "--checkpoint", "pretrained:small"],
            f"scene list {root}/scannetv2_test.txt: 1 of its 2 scenes are not folders of {root}/test, "
            "the first: scene0710_00",
        )
    )
    for args, message in cases:
        capsys.readouterr()
        with unchecked():  # argparse lets "--split dev" through: DataConfig's own one line is the point
            assert main(["eval", *args, *out]) == 2, args
        assert capsys.readouterr().err.strip().splitlines() == [f"llrmpp: error: {message}"]
    assert not os.path.exists(tmp_path / "ev")

    exp = load_experiment(str(cfg_file))
    save_params(str(tmp_path / "p"), init_params(jax.random.key(3), exp.model, 2, 32, 32), exp.model)
    assert main(["eval", "--config", str(cfg_file), "--checkpoint", str(tmp_path / "p"), "--split", "val", *out]) == 0
    printed = capsys.readouterr().out.splitlines()
    assert f"held-out data: split val: the first 100 scenes named in {root}/scannetv2_val.txt in {root}/val" in printed
    assert [x for x in printed if x.startswith("eval scene")][0].startswith(
        "eval scene scene0011_00: 2 inputs, 2 targets"
    )
    rows = open(tmp_path / "ev" / "per_scene.csv").read().splitlines()
    assert {r.split(",")[0] for r in rows[1:]} == {"scene0011_00"}


def test_train_init_starts_from_the_given_weights_and_a_resume_ignores_them(tmp_path):
    """``init``: a params folder (drawn weights, not the run's own init) is where stage 1
    starts; at learning rate 0 the trained params equal the saved ones exactly. Rerun longer
    with other weights as ``init``, the run resumes from its checkpoint instead, and its
    ``train_log.json`` keeps the first call's steps and ``init``; a step redone after a lost
    checkpoint is logged once."""
    import dataclasses

    import jax

    from llrmpp_jax.model import init_params
    from llrmpp_jax.params_io import save_params
    from llrmpp_jax.trainer import train

    def frozen(steps):
        exp = micro_experiment(steps)
        return dataclasses.replace(exp, eval_every=0, stages=(dataclasses.replace(exp.stages[0], lr=0.0),))

    exp = frozen(1)
    start = jax.tree.map(
        lambda p: p + jax.random.normal(jax.random.key(5), p.shape, p.dtype),
        init_params(jax.random.key(3), exp.model, 2, 32, 32),
    )
    other = jax.tree.map(lambda p: p - 1.0, start)
    save_params(str(tmp_path / "start"), start, exp.model)
    save_params(str(tmp_path / "other"), other, exp.model)
    work = str(tmp_path / "run")
    first = train(exp, work, progress=False, init=str(tmp_path / "start"))
    for g, w in zip(jax.tree.leaves(first["params"]), jax.tree.leaves(start)):
        np.testing.assert_array_equal(np.asarray(g), np.asarray(w))
    second = train(frozen(2), work, progress=False, init=str(tmp_path / "other"))
    assert [h["step"] for h in second["history"]] == [2]
    for g, w in zip(jax.tree.leaves(second["params"]), jax.tree.leaves(start)):
        np.testing.assert_array_equal(np.asarray(g), np.asarray(w))
    log = json.load(open(os.path.join(work, "train_log.json")))
    assert [h["step"] for h in log["history"]] == [1, 2] and log["init"] == str(tmp_path / "other")
    # step 2's checkpoint lost: the rerun redoes step 2, and its log holds step 2 once
    shutil.rmtree(os.path.join(work, "checkpoints", "s1", "2"))
    third = train(frozen(2), work, progress=False)
    assert [h["step"] for h in third["history"]] == [2]
    log = json.load(open(os.path.join(work, "train_log.json")))
    assert [h["step"] for h in log["history"]] == [1, 2] and log["init"] == str(tmp_path / "other")


def test_train_init_of_another_architecture_is_one_line(tmp_path):
    """Weights of a model with other head widths as ``--init``: one line naming the first
    differing parameter and both shapes, before any training."""
    import jax

    from llrmpp_jax.model import init_params
    from llrmpp_jax.params_io import save_params

    exp = micro_experiment(1)
    wide = replace(exp.model, head=replace(exp.model.head, feature_dim=16))
    save_params(str(tmp_path / "wide"), init_params(jax.random.key(0), wide, 2, 32, 32), wide)
    res = _run_cli(
        "train",
        "--config",
        str(_micro_experiment_file(tmp_path, 1)),
        "--workdir",
        str(tmp_path / "run"),
        "--init",
        str(tmp_path / "wide"),
    )
    assert res.returncode == 2
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and "first mismatch" in lines[0] and "(another architecture?" in lines[0], res.stderr
    assert not os.path.exists(tmp_path / "run" / "checkpoints")


def test_workdir_params_come_from_the_curriculum_s_last_stage(tmp_path):
    """Stage ``a`` trained with a config naming only ``a``, then ``b`` with the curriculum
    ``(a, b)`` (as the ``small`` recipe's first stage was, then the whole): a workdir loads ``b``'s params,
    though ``a``'s folder sorts first and its config does not know ``b``."""
    import dataclasses

    import jax

    from llrmpp_jax import train as T
    from llrmpp_jax.model import init_params
    from llrmpp_jax.params_io import load_params

    whole = micro_experiment(1)
    whole = dataclasses.replace(
        whole, stages=(dataclasses.replace(whole.stages[0], name="a"), dataclasses.replace(whole.stages[0], name="b"))
    )
    first = dataclasses.replace(whole, stages=whole.stages[:1])
    params = init_params(jax.random.key(0), whole.model, 2, 32, 32)
    opt = T.make_optimizer(T.OptimizerConfig(total_steps=1, warmup_steps=0))
    later = jax.tree.map(lambda p: p + 1.0, params)
    work = tmp_path / "run" / "checkpoints"
    T.save_checkpoint(work / "a", T.init_train_state(params, opt, jax.random.key(1)), config=first)
    T.save_checkpoint(work / "b", T.init_train_state(later, opt, jax.random.key(1)), config=whole)
    got, cfg = load_params(str(tmp_path / "run"))
    assert cfg == whole.model
    for g, w in zip(jax.tree.leaves(got), jax.tree.leaves(later)):
        np.testing.assert_array_equal(np.asarray(g), np.asarray(w))


def test_distributed_train_runs_itself_under_the_supervisor(tmp_path, monkeypatch):
    """``train --distributed`` re-runs the same command as a supervised child (so the
    coordinator's death is one line: ``tests/train/test_multihost.py``), and the child, which
    sees ``LLRMPP_SUPERVISED=1``, does not supervise itself again."""
    import llrmpp_jax.train.supervise as supervise

    calls = []
    monkeypatch.setattr(supervise, "run_supervised", lambda command, hint, log: calls.append((command, hint, log)) or 7)
    monkeypatch.delenv(supervise.ENV, raising=False)
    argv = ["train", "--config", "demo", "--workdir", str(tmp_path / "w"), "--distributed", "--heartbeat-timeout", "5"]
    assert main(argv) == 7
    ((command, hint, log),) = calls
    assert command == [sys.executable, "-m", "llrmpp_jax.cli", *argv]
    assert hint == f"resume from the last complete checkpoint in {tmp_path / 'w' / 'checkpoints'}"
    assert log.startswith(str(tmp_path / "w" / "logs" / "jax_abort_"))
    monkeypatch.setenv(supervise.ENV, "1")
    monkeypatch.setattr("jax.distributed.initialize", lambda **kw: (_ for _ in ()).throw(RuntimeError("initialize")))
    with pytest.raises(RuntimeError, match="initialize"):  # the child goes on to start JAX's distributed runtime
        main(argv)
    assert len(calls) == 1

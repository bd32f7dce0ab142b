"""The package stands alone: recipes load by name, benchmarks run as package modules, and no
module reaches for the repository's ``experiments/`` folder."""

import ast
import importlib
import os

import pytest

import llrmpp_jax
from llrmpp_jax.benchmarks.suite import BENCHMARKS
from llrmpp_jax.cli import main
from llrmpp_jax.experiment import ExperimentConfig, load_experiment
from llrmpp_jax.recipes import recipe_names, recipe_path
from tests.helpers.typechecks import unchecked

PACKAGE = os.path.dirname(os.path.abspath(llrmpp_jax.__file__))

# String constants in the package that name a path under experiments/ for a reason other
# than reading this checkout's files: (module, string) -> why.
ALLOWED: dict[tuple[str, str], str] = {}


def test_the_recipes_commands_and_docs_name_are_shipped():
    assert {"demo", "small", "long_lrm", "dl3dv", "scannet"} <= set(recipe_names())


@pytest.mark.parametrize("name", recipe_names())
def test_each_recipe_loads_by_name_and_stands_alone(name):
    exp = load_experiment(name)
    assert isinstance(exp, ExperimentConfig) and exp.stages
    assert load_experiment(recipe_path(name)) == exp  # by path, the same  # pyright: ignore[reportArgumentType] -- every listed recipe has a path
    tree = ast.parse(open(recipe_path(name)).read())  # pyright: ignore[reportArgumentType] -- as above
    imported = {a.name for n in ast.walk(tree) if isinstance(n, ast.Import) for a in n.names} | {
        n.module for n in ast.walk(tree) if isinstance(n, ast.ImportFrom)
    }
    assert not any(m.startswith("llrmpp_jax.recipes") for m in imported), imported  # pyright: ignore[reportOptionalMemberAccess] -- recipes use absolute imports only
    calls = [n.func for n in ast.walk(tree) if isinstance(n, ast.Call)]
    assert not any(isinstance(f, ast.Name) and f.id == "load_experiment" for f in calls), "a recipe loads another"


def test_the_paper_recipes_take_long_lrm_s_learning_rate_schedule():
    """dl3dv and scannet: every stage warms up, then follows Long-LRM's cosine over its
    1,000,000-step horizon, so no stage ends below 99% of its peak rate (DL3DV's 60K-step
    stage 1 ends at 99.17%); the cosine over the stage stays an option; a bad name is one line."""
    from llrmpp_jax.errors import UserError
    from llrmpp_jax.experiment import StageConfig
    from llrmpp_jax.train.optimizer import make_schedule
    from llrmpp_jax.trainer import optimizer_config

    for name in ("dl3dv", "scannet"):
        for stage in load_experiment(name).stages:
            cfg = optimizer_config(stage)
            assert stage.lr_schedule == "long_lrm" and cfg.total_steps == 1_000_000, (name, stage.name)
            assert 0.99 * stage.lr <= float(make_schedule(cfg)(stage.steps)) <= stage.lr, (name, stage.name)  # pyright: ignore[reportArgumentType] -- float()/int() of a scalar array
    own = StageConfig(
        "s", steps=100, global_batch=1, num_inputs=1, num_targets=1, resize_h=None, warmup_steps=10, lr_schedule="stage"
    )
    assert optimizer_config(own).total_steps == 100 and float(make_schedule(optimizer_config(own))(100)) == 0.0  # pyright: ignore[reportArgumentType] -- float()/int() of a scalar array
    with pytest.raises(UserError, match="lr_schedule must be 'long_lrm' or 'stage', got 'constant'"), unchecked():
        StageConfig("s", steps=1, global_batch=1, num_inputs=1, num_targets=1, resize_h=None, lr_schedule="constant")  # pyright: ignore[reportArgumentType] -- a bad value on purpose: the test wants its error


def test_the_long_lrm_recipe_is_long_lrm_s_training_recipe():
    """Long-LRM's configs (reference facts §2.1-2.2, §3.3-3.4) written out by hand: its
    architecture (what ``llrmpp convert`` converts to), MSE + 1.0 VGG19 perceptual + 0.1
    opacity, uniform targets, order augmentations everywhere, zoom and pruning 0.6 / 0.1 at
    960x540 only, 4e-4 with 2000 warmup steps then 4e-5, its 1,000,000-step cosine, the
    gradient-norm guard at 50."""
    from llrmpp_jax import config as C

    exp = load_experiment("long_lrm")
    assert exp.model == C.long_lrm()
    assert (exp.perceptual_weight, exp.perceptual_net, exp.opacity_weight) == (1.0, "vgg19", 0.1)
    assert exp.skip_grad_norm_above == 50.0 and exp.bf16 and exp.gaussian_depth_weight == 0.0
    got = [
        (
            s.resize_h,
            s.square_crop,
            s.num_inputs,
            s.num_targets,
            s.lr,
            s.warmup_steps,
            s.min_span,
            s.max_span,
            s.zoom_min,
            exp.model_of(s).head.prune_ratio,
            exp.model_of(s).head.prune_random_ratio,
        )
        for s in exp.stages
    ]
    assert got == [
        (256, True, 32, 8, 4e-4, 2000, 64, 128, 1.0, 0.0, 0.0),
        (512, True, 32, 8, 4e-5, 0, 64, 128, 1.0, 0.0, 0.0),
        (540, False, 32, 8, 4e-5, 0, None, None, 0.77, 0.6, 0.1),
    ]
    assert all(
        (s.input_weight, s.reverse_prob, s.shuffle_prob, s.lr_schedule) == (1.0, 0.5, 0.5, "long_lrm")
        for s in exp.stages
    )


def test_the_small_recipe_is_the_shipped_model_s():
    from llrmpp_jax.pretrained import load_pretrained

    exp = load_experiment("small")
    assert exp.name == "small" and [s.name for s in exp.stages] == ["accel", "sharpen"]
    _, cfg = load_pretrained("small", exp.model)  # checks the shipped config against the recipe's
    assert cfg == exp.model


def test_an_unknown_config_name_is_one_line_listing_the_recipes(capsys):
    assert main(["train", "--config", "smal", "--workdir", "/tmp/never_made"]) == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1, lines
    assert lines[0].startswith("llrmpp: error: config file not found: smal ")
    assert all(name in lines[0] for name in recipe_names())
    assert not os.path.exists("/tmp/never_made")


def test_every_benchmark_llrmpp_bench_runs_is_a_package_module():
    for name in BENCHMARKS:
        module = importlib.import_module(f"llrmpp_jax.benchmarks.{name}")
        assert callable(module.main), name


def _docstring_nodes(tree: ast.AST) -> set[int]:
    out = set()
    for node in ast.walk(tree):
        if isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)) and node.body:
            first = node.body[0]
            if isinstance(first, ast.Expr) and isinstance(first.value, ast.Constant):
                out.add(id(first.value))
    return out


def _names_experiments(text: str) -> bool:
    """A path with an ``experiments`` component."""
    return "experiments" in text.replace("\\", "/").split("/")


def _imports_experiments(module: str) -> bool:
    """``experiments.*`` or one of its scripts put on ``sys.path`` (``bench_train``, ...)."""
    return module.split(".")[0] == "experiments" or module.startswith("bench_")


def test_no_module_reaches_for_the_experiments_folder():
    """Imports and string constants (docstrings aside: citations of evidence, not paths the
    code opens) of every module in the package: none names the repository's experiments/
    folder or imports its scripts, so an installed wheel has everything it reads."""
    found = []
    for root, _, files in os.walk(PACKAGE):
        for f in files:
            if not f.endswith(".py"):
                continue
            path = os.path.join(root, f)
            rel = os.path.relpath(path, PACKAGE)
            tree = ast.parse(open(path).read(), path)
            docs = _docstring_nodes(tree)
            for node in ast.walk(tree):
                if isinstance(node, ast.Import):
                    found += [(rel, a.name) for a in node.names if _imports_experiments(a.name)]
                elif isinstance(node, ast.ImportFrom) and node.module and _imports_experiments(node.module):
                    found.append((rel, node.module))
                elif (
                    isinstance(node, ast.Constant)
                    and isinstance(node.value, str)
                    and id(node) not in docs
                    and _names_experiments(node.value)
                    and (rel, node.value) not in ALLOWED
                ):
                    found.append((rel, node.value))
    assert not found, found

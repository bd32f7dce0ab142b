"""The package stands alone: its recipes load by name."""

import ast
import os

import pytest

from llrmpp_jax.cli import main
from llrmpp_jax.experiment import ExperimentConfig, load_experiment
from llrmpp_jax.recipes import recipe_names, recipe_path


def test_the_recipes_commands_and_docs_name_are_shipped():
    assert {"demo", "small", "long_lrm", "dl3dv", "scannet"} <= set(recipe_names())


@pytest.mark.parametrize("name", recipe_names())
def test_each_recipe_loads_by_name_and_stands_alone(name):
    exp = load_experiment(name)
    assert isinstance(exp, ExperimentConfig) and exp.stages
    assert load_experiment(recipe_path(name)) == exp  # by path, the same
    tree = ast.parse(open(recipe_path(name)).read())
    imported = {a.name for n in ast.walk(tree) if isinstance(n, ast.Import) for a in n.names} | \
               {n.module for n in ast.walk(tree) if isinstance(n, ast.ImportFrom)}
    assert not any(m.startswith("llrmpp_jax.recipes") for m in imported), imported
    calls = [n.func for n in ast.walk(tree) if isinstance(n, ast.Call)]
    assert not any(isinstance(f, ast.Name) and f.id == "load_experiment" for f in calls), "a recipe loads another"


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

"""The experiment recipes that ship with the package, each loadable by name.

A recipe is a module here with a ``get_config()`` returning an
:class:`~llrmpp_jax.experiment.ExperimentConfig` (big_vision style: its header gives the run
command). ``llrmpp train --config small`` and :func:`llrmpp_jax.experiment.load_experiment`
take a recipe's name or the path of any such Python file:

* ``demo`` -- the tiny model ``llrmpp demo`` trains from scratch on a CPU in minutes;
* ``small`` -- the shipped model ``pretrained:small`` (procedural scenes);
* ``dl3dv``, ``scannet`` -- the paper's curricula (Tables 8 and 9);
* ``long_lrm`` -- Long-LRM: the architecture of the official PyTorch checkpoints (what
  ``llrmpp convert`` converts to) and its own DL3DV training recipe.

Each recipe is self-contained: none imports another.
"""

from __future__ import annotations

import os

RECIPES_DIR = os.path.dirname(os.path.abspath(__file__))


def recipe_names() -> list[str]:
    """The shipped recipes' names, sorted."""
    return sorted(f[:-3] for f in os.listdir(RECIPES_DIR) if f.endswith(".py") and not f.startswith("_"))


def recipe_path(name: str) -> str | None:
    """The file of recipe ``name``, or None when no recipe has that name."""
    return os.path.join(RECIPES_DIR, f"{name}.py") if name in recipe_names() else None

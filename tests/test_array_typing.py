"""The shape legend is checked: the suite runs every ``llrmpp_jax`` function under jaxtyping
with beartype (``conftest.py``), and every axis name an annotation uses has its line in
``llrmpp_jax.array_typing``'s legend."""

import ast
import pathlib
import re

import jax.numpy as jnp
import jaxtyping
import pytest

import llrmpp_jax
from llrmpp_jax import array_typing
from llrmpp_jax.nn.norms import rms_norm
from llrmpp_jax.splat.projection import camera_is_valid
from tests.helpers.typechecks import unchecked

PACKAGE = pathlib.Path(llrmpp_jax.__file__).parent
ARRAY_KINDS = {"Float", "Int", "Bool", "Shaped", "UInt32"}


def legend() -> list[str]:
    """The names of the docstring's legend lines (``    NAME   meaning``), in order."""
    return re.findall(r"^ {4}(\*?\w+) {2,}\S", array_typing.__doc__, flags=re.M)  # pyright: ignore[reportArgumentType, reportCallIssue] -- the module has its legend docstring


def annotated_axes() -> dict[str, set[str]]:
    """Axis name -> the modules whose ``Float[..., "..."]``-style annotations use it
    (symbolic sizes such as ``F+6`` give their names; ``...``, numbers and ``_`` none)."""
    uses: dict[str, set[str]] = {}
    for path in sorted(PACKAGE.rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            if not (
                isinstance(node, ast.Subscript)
                and isinstance(node.value, ast.Name)
                and node.value.id in ARRAY_KINDS
                and isinstance(node.slice, ast.Tuple)
            ):
                continue
            shape = node.slice.elts[1]
            assert isinstance(shape, ast.Constant), f"{path}: shape of {ast.unparse(node)} is not a literal"
            for axis in shape.value.split():  # pyright: ignore[reportAttributeAccessIssue, reportOptionalMemberAccess] -- the shape is a str constant (asserted above)
                star = "*" if axis.lstrip("#").startswith("*") else ""  # pyright: ignore[reportArgumentType] -- the shape is a str constant (asserted above)
                for name in re.findall(r"[A-Za-z]\w*", axis):  # pyright: ignore[reportArgumentType, reportCallIssue] -- as above
                    uses.setdefault(star + name, set()).add(str(path.relative_to(PACKAGE.parent)))
    return uses


def test_every_axis_name_has_one_legend_line():
    names = legend()
    assert len(names) == len(set(names)), f"legend names twice: {sorted(n for n in names if names.count(n) > 1)}"
    missing = {name: sorted(where) for name, where in annotated_axes().items() if name not in names}
    assert not missing, f"axis names with no line in llrmpp_jax/array_typing.py's legend: {missing}"


def test_annotations_are_checked():
    """The oracle that the hook is on: wrong shapes raise jaxtyping's error before the body
    runs, whether an axis has a fixed size or a name another argument fixed."""
    with pytest.raises(jaxtyping.TypeCheckError, match="intrinsics"):
        camera_is_valid(jnp.eye(4), jnp.ones(5))  # the body alone reads [0], [1] and passes
    with pytest.raises(jaxtyping.TypeCheckError, match="scale"):
        rms_norm(jnp.ones((2, 4)), jnp.ones(5))  # C: 4 from x, 5 from scale
    assert bool(camera_is_valid(jnp.eye(4), jnp.ones(4)))


def test_unchecked_turns_the_checks_off_for_its_block_only():
    with unchecked():
        assert bool(camera_is_valid(jnp.eye(4), jnp.ones(5)))
    with pytest.raises(jaxtyping.TypeCheckError):
        camera_is_valid(jnp.eye(4), jnp.ones(5))

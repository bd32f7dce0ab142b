"""The plan's program registry: every name builds the program it names, and the catalog (read by
the command line without JAX) lists exactly the registry."""

from llrmpp_jax.plan.catalog import GROUPS, PROGRAM_NAMES
from llrmpp_jax.plan.programs import PROGRAMS, program


def test_every_program_carries_its_registry_name():
    assert tuple(PROGRAMS) == PROGRAM_NAMES
    assert set(GROUPS["paper"]) | set(GROUPS["tiny"]) == set(PROGRAM_NAMES)
    for name in PROGRAM_NAMES:
        assert program(name).name == name

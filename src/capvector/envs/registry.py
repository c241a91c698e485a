"""The benchmark suites by name: built-in ones, those of installed packages (entry point group
``capvector.envs``), and ``module:Suite`` names, as backbone families are found
(:mod:`capvector.registry`).

A package outside capvector adds a suite by subclassing :class:`~capvector.envs.base.Suite` in a
module that registers it (``@SUITES.register("my_suite")``) and naming that module in its
``pyproject.toml``::

    [project.entry-points."capvector.envs"]
    my_suite = "my_package.suite"

Importing this module imports no simulator: a suite's module imports its simulator only when an
episode starts.
"""

from __future__ import annotations

from collections.abc import Sequence

from capvector.envs.base import Spec, Suite
from capvector.errors import CapVectorError, unknown_name
from capvector.registry import Registry

ENTRY_POINT_GROUP = "capvector.envs"

SUITES: Registry[type[Suite]] = Registry(
    "benchmark suite",
    modules=(
        "capvector.envs.robosuite.suite",
        "capvector.envs.libero.suite",
        "capvector.envs.metaworld.suite",
    ),
    group=ENTRY_POINT_GROUP,
    base=Suite,
)


def get_suite(name: str) -> Suite:
    """The suite registered as ``name`` (or named ``module:Suite``), ready to start episodes."""
    return SUITES.get(name)()


def suite_of(spec: Spec) -> Suite:
    """The suite that runs ``spec`` (its ``SUITE``)."""
    return get_suite(type(spec).SUITE)


def suite_for_task_set(task_set: str) -> Suite:
    """The registered suite whose :attr:`~capvector.envs.base.Suite.task_sets` holds
    ``task_set`` (``Lift``: robosuite, ``libero_spatial``: LIBERO); one line naming the close
    names otherwise. This is how a command line or a config entry reaches its suite."""
    owners = {name: get_suite(name) for name in registered_suites()}
    found = [suite for suite in owners.values() if task_set in suite.task_sets]
    if len(found) > 1:
        names = ", ".join(suite.name for suite in found)
        raise CapVectorError(f"task set {task_set!r} is claimed by several suites: {names}")
    if not found:
        known = [name for suite in owners.values() for name in suite.task_sets]
        raise unknown_name("task or task set", task_set, known)
    return found[0]


def check_specs(specs: Sequence[Spec]) -> None:
    """Each suite's :meth:`~capvector.envs.base.Suite.check` of its specs, before any episode."""
    by_suite: dict[str, list[Spec]] = {}
    for spec in specs:
        by_suite.setdefault(type(spec).SUITE, []).append(spec)
    for name, own in by_suite.items():
        get_suite(name).check(own)


def registered_suites() -> list[str]:
    """Every registered suite: the built-in ones and those of installed entry points."""
    return SUITES.names()


__all__ = [
    "ENTRY_POINT_GROUP",
    "SUITES",
    "check_specs",
    "get_suite",
    "registered_suites",
    "suite_for_task_set",
    "suite_of",
]

"""Shared fixtures (seeded generators, never a global seed; the one shared ci-profile workflow
run) and the order in which pytest-xdist's workers take the tests.

With ``-n auto`` (the project's default, ``pyproject.toml``: two workers on two cores) the tests are spread over
worker processes by group (``--dist loadgroup``): every test that reads the shared ci-profile run is
in the group ``ci_run``, so one worker makes the run once and then reads it, and every other
module whose tests share a module-scoped fixture is a group of its own, so the fixture is built
once. The ``ci_run`` group goes first (it is the longest), then the Slurm test's module (on the
other worker meanwhile), then the modules marked ``slow``, so that the short tests fill the
workers' time at the end.

The tests that read the shared ci-profile run (the ci profile's Pillow tables made by the
workflow and checked: about 6 minutes of the run's jobs on two cores) are the ``tables`` tier,
which the project's default options deselect (``pyproject.toml``: ``-m "not tables"``):
``python3 -m pytest -m tables`` runs them, as CI does after the suite (``.ci/run``).
"""

from __future__ import annotations

import numpy as np
import pytest

from _workflow import ci_run as _ci_run


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(20261122)


@pytest.fixture(scope="session")
def pillow_ci():
    """The ci-profile Pillow contract and its built asset (built once for the whole run;
    its arrays are read-only)."""
    from knockgs_core.assets import build_asset
    from knockgs_core.contract import load_contract

    contract = load_contract("pillow", "ci")
    return contract, build_asset(contract)


@pytest.fixture(scope="session")
def ci_run(tmp_path_factory):
    """The scratch workflow folder of the shared ci-profile run of the Pillow (``_workflow.ci_run``:
    main, render, diagnostics, probe-shift, passive and ladder tables, audits), made once per
    test run. Read only: a test that changes files works on ``_workflow.copy_run``'s copy."""
    return _ci_run(tmp_path_factory)


def _shares_a_module_fixture(item) -> bool:
    info = getattr(item, "_fixtureinfo", None)
    if info is None:
        return False
    return any(defs and defs[-1].scope == "module" for defs in info.name2fixturedefs.values())


#: the groups that start first, in this order: the shared ci run (the longest, on one worker),
#: then the Slurm test (a cluster's start and queue waits, on the other worker meanwhile)
FIRST = ("ci_run", "test_slurm")


@pytest.hookimpl(tryfirst=True)
def pytest_collection_modifyitems(config, items):
    """Group and order the tests (module docs); mark every test that reads the shared ci run
    ``tables`` (and ``slow``): the project's default ``-m "not tables"`` leaves them to
    ``pytest -m tables``, which CI runs after the suite."""
    slow_modules = {item.path for item in items if item.get_closest_marker("slow")}
    for item in items:
        if "ci_run" in item.fixturenames:         # whatever its group: deselected by default
            item.add_marker(pytest.mark.tables)
            item.add_marker(pytest.mark.slow)
        if item.get_closest_marker("xdist_group"):
            continue
        if "ci_run" in item.fixturenames:
            item.add_marker(pytest.mark.xdist_group("ci_run"))
        elif _shares_a_module_fixture(item):
            item.add_marker(pytest.mark.xdist_group(item.path.stem))

    def rank(item):
        group = item.get_closest_marker("xdist_group")
        name = group.args[0] if group is not None and group.args else None
        if name in FIRST:
            return FIRST.index(name)
        return len(FIRST) + (0 if item.path in slow_modules else 1)

    items.sort(key=rank)  # stable: the order within each rank is the collection's


def pytest_configure(config):
    """Under ``--dist loadgroup`` pytest-xdist names each grouped item ``NODEID@GROUP`` on the
    workers, which is how it sends a group to one worker. pytest 9.2 keeps node ids where
    pytest-xdist 3.8 no longer reaches them, so every group would be spread over the workers, and
    a worker that needs a shared run would wait for the other to build it: stop, saying why."""
    version = tuple(int(p) for p in pytest.__version__.split(".")[:2] if p.isdigit())
    workers = config.getoption("numprocesses", default=None)
    if workers not in (None, 0) and config.getoption("dist", default="no") == "loadgroup" and version >= (9, 2):
        raise pytest.UsageError(f"pytest {pytest.__version__} breaks pytest-xdist's --dist loadgroup (the tests' "
                                "groups would be spread over the workers): pip install -e '.[test]' (pytest < 9.2)")

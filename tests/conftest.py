"""Shared fixtures: seeded generators (never a global seed)."""

from __future__ import annotations

import numpy as np
import pytest


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

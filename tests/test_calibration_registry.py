"""The calibration method vocabulary: canonical names, aliases, options, and who accepts them."""

from __future__ import annotations

import inspect
import json
import subprocess
import sys
from pathlib import Path

import pytest

import knockgs_core.calibration as calibration
from knockgs_core.calibration import (
    DEPLOYABLE_METHODS,
    METHOD_ALIASES,
    METHOD_NAMES,
    METHOD_OPTIONS,
    METHODS,
    ORACLE_METHOD,
    calibrate,
    canonical_method,
)
from knockgs_core.calibration.oracle import ParameterNearestOracle
from knockgs_core.errors import InputError

FICUS = Path(__file__).parent / "data" / "knockgs-ficus"

#: the method column of the paper's tables, in order
TABLE_ORDER = ("fixed_default", "response_nearest", "response_knn", "global_ridge", "local_ridge",
               "parameter_nearest_oracle")


def test_names_are_the_table_names_in_table_order():
    assert METHOD_NAMES == TABLE_ORDER
    assert DEPLOYABLE_METHODS == TABLE_ORDER[:5]
    assert ORACLE_METHOD == TABLE_ORDER[5]
    assert tuple(METHODS) == DEPLOYABLE_METHODS
    assert METHOD_ALIASES == {"default": "fixed_default", "nearest": "response_nearest", "knn": "response_knn"}


@pytest.mark.parametrize("name", METHOD_NAMES)
def test_canonical_names_map_to_themselves(name):
    assert canonical_method(name) == name


@pytest.mark.parametrize("alias, name", sorted(METHOD_ALIASES.items()))
def test_aliases_map_to_canonical_names(alias, name):
    assert canonical_method(alias) == name


@pytest.mark.parametrize("bad", ["lasso", "KNN", "", None, 3])
def test_unknown_name_lists_names_and_aliases(bad):
    with pytest.raises(ValueError) as err:
        canonical_method(bad)
    message = str(err.value)
    assert f"unknown method {bad!r}" in message
    assert "allowed: " + ", ".join(METHOD_NAMES) in message
    assert all(alias in message for alias in METHOD_ALIASES)


def test_options_are_the_estimators_keyword_arguments():
    assert tuple(METHOD_OPTIONS) == METHOD_NAMES
    classes = {**METHODS, ORACLE_METHOD: ParameterNearestOracle}
    for name, cls in classes.items():
        params = inspect.signature(cls).parameters.values()
        assert all(p.kind is p.KEYWORD_ONLY for p in params), name
        assert tuple(p.name for p in params) == METHOD_OPTIONS[name], name
        assert cls.method == name  # the name an Estimate carries


@pytest.mark.parametrize("alias, name", sorted(METHOD_ALIASES.items()))
def test_calibrate_accepts_aliases(alias, name):
    by_name = calibrate(FICUS / "library.csv", FICUS / "queries.csv", name)
    assert calibrate(FICUS / "library.csv", FICUS / "queries.csv", alias) == by_name
    assert by_name["method"] == name


def test_calibrate_rejects_the_oracle_and_unknown_names():
    for bad in (ORACLE_METHOD, "lasso"):
        with pytest.raises(InputError) as err:
            calibrate(FICUS / "library.csv", FICUS / "queries.csv", bad)
        assert err.value.field == "method"
        assert "allowed: " + ", ".join(DEPLOYABLE_METHODS) in str(err.value)


def test_option_errors_name_the_canonical_method():
    with pytest.raises(InputError, match="not an option of method 'response_knn'"):
        calibrate(FICUS / "library.csv", FICUS / "queries.csv", "knn", alpha=0.1)


def test_importing_calibration_is_light():
    code = ("import sys, knockgs_core.calibration; "
            "print(sorted(m for m in sys.modules if m == 'warp' or m.startswith(('warp.', 'knockgs_core.sim', "
            "'knockgs_core.rollout', 'pandas'))))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, check=True)
    assert out.stdout.strip() == "[]"


def test_namespace_exports_the_vocabulary():
    for name in ("METHOD_NAMES", "DEPLOYABLE_METHODS", "ORACLE_METHOD", "METHOD_ALIASES", "METHOD_OPTIONS",
                 "canonical_method", "METHODS"):
        assert name in calibration.__all__


# ------------------------------------------------------------------ frozen_estimate


@pytest.fixture(scope="module")
def experiments():
    from knockgs_core import experiments

    return experiments


@pytest.mark.parametrize("alias, name", sorted(METHOD_ALIASES.items()))
def test_frozen_estimate_takes_canonical_names_and_aliases(experiments, alias, name):
    lib, q = FICUS / "library.csv", FICUS / "queries.csv"
    doc = experiments.frozen_estimate(name, lib, q, config_hash="h")
    assert doc == experiments.frozen_estimate(alias, lib, q, config_hash="h")
    assert doc["method"] == doc["table_method"] == name
    assert doc["deployable"] is True and doc["config_hash"] == "h"
    assert doc["predictions"] == calibrate(lib, q, name)["predictions"]
    json.dumps(doc, allow_nan=False)


def test_frozen_estimate_options_and_all_deployable_names(experiments):
    lib, q = FICUS / "library.csv", FICUS / "queries.csv"
    for name in DEPLOYABLE_METHODS:
        assert experiments.frozen_estimate(name, lib, q)["method"] == name
    doc = experiments.frozen_estimate("response_knn", lib, q, {"k": "cv"})
    assert doc["params"]["k"] == 2 and doc["params"]["k_selection"] == "cv"


@pytest.mark.parametrize("bad, message", [(ORACLE_METHOD, "is not deployable"), ("lasso", "unknown method 'lasso'")])
def test_frozen_estimate_rejects_the_oracle_and_unknown_names(experiments, bad, message):
    with pytest.raises(InputError) as err:
        experiments.frozen_estimate(bad, FICUS / "library.csv", FICUS / "queries.csv")
    assert err.value.field == "method" and message in str(err.value)


def test_oracle_estimate_takes_its_registry_options():
    """The oracle's options (METHOD_OPTIONS) reach the estimator; an unknown one is refused."""
    import pandas as pd

    from knockgs_core.experiments import oracle_estimate

    truth = pd.read_csv(FICUS / "ground_truth.csv")
    lib = FICUS / "library.csv"
    plain = oracle_estimate(lib, truth)
    std = oracle_estimate(lib, truth, {"metric": "standardized"})
    assert plain["params"] == {} and std["params"] == {"metric": "standardized"}
    assert [p["case_name"] for p in std["predictions"]] == list(truth["case_name"])
    assert all(p["details"]["metric"] == "standardized" for p in std["predictions"])
    with pytest.raises(InputError, match="method_params.parameter_nearest_oracle"):
        oracle_estimate(lib, truth, {"k": 3})
    with pytest.raises(InputError, match="metric"):
        oracle_estimate(lib, truth, {"metric": "cosine"})

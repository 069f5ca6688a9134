"""``knockgs calibrate``: output file, exit codes, one-line errors."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from knockgs_core.calibration import DEPLOYABLE_METHODS, METHOD_ALIASES, ORACLE_METHOD, calibrate, joint_error_pct
from knockgs_core.cli import main

FICUS = Path(__file__).parent / "data" / "knockgs-ficus"


def _no_nan(token):
    raise AssertionError(f"non-JSON float {token} in output")


def read_json(path):
    return json.loads(Path(path).read_text(), parse_constant=_no_nan)


def run_cli(*args):
    return main(["calibrate", *map(str, args)])


def test_writes_the_calibrate_result(tmp_path):
    out = tmp_path / "sub" / "est.json"
    rc = run_cli("--library", FICUS / "library.csv", "--queries", FICUS / "queries.csv",
                 "--method", "local_ridge", "--output", out)
    assert rc == 0
    result = read_json(out)
    assert result == calibrate(FICUS / "library.csv", FICUS / "queries.csv", "local_ridge")
    assert result["method"] == "local_ridge"
    assert result["params"]["k"] == 10 and result["params"]["alpha"] == 0.001
    truth = pd.read_csv(FICUS / "ground_truth.csv").set_index("case_name")
    pred = pd.DataFrame(result["predictions"]).set_index("case_name").loc[truth.index]
    err = joint_error_pct(pred[["E_scale", "density_scale"]].to_numpy(), truth.to_numpy(float))
    assert round(float(np.mean(err)), 5) == 0.62909


def test_options_and_label_columns_in_queries(tmp_path):
    # queries with the ground-truth labels joined in: ignored, same estimates
    queries = pd.read_csv(FICUS / "queries.csv").merge(pd.read_csv(FICUS / "ground_truth.csv"))
    labelled = tmp_path / "labelled.csv"
    queries.to_csv(labelled, index=False)
    runs = ((FICUS / "queries.csv", tmp_path / "a.json"), (labelled, tmp_path / "b.json"))
    for path, out in runs:
        assert run_cli("--library", FICUS / "library.csv", "--queries", path, "--method", "knn",
                       "--k", "cv", "--output", out) == 0
    a, b = read_json(tmp_path / "a.json"), read_json(tmp_path / "b.json")
    assert a == b and a["params"]["k"] == 2 and a["params"]["k_selection"] == "cv"
    assert run_cli("--library", FICUS / "library.csv", "--queries", labelled,
                   "--method", "global_ridge", "--alpha", "0.01",
                   "--output", tmp_path / "c.json") == 0
    assert read_json(tmp_path / "c.json")["params"]["alpha"] == 0.01


@pytest.mark.parametrize("alias", sorted(METHOD_ALIASES))
def test_canonical_names_and_aliases_give_the_same_file(tmp_path, alias):
    canonical = METHOD_ALIASES[alias]
    outs = [tmp_path / "canonical.json", tmp_path / "alias.json"]
    for method, out in zip((canonical, alias), outs):
        assert run_cli("--library", FICUS / "library.csv", "--queries", FICUS / "queries.csv",
                       "--method", method, "--output", out) == 0
    assert outs[0].read_bytes() == outs[1].read_bytes()
    assert read_json(outs[0])["method"] == canonical


def test_method_choices_come_from_the_registry(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["calibrate", "--help"])
    assert exc.value.code == 0
    text = " ".join(capsys.readouterr().out.split())
    for name in (*DEPLOYABLE_METHODS, *METHOD_ALIASES):
        assert name in text
    assert ORACLE_METHOD not in text


@pytest.mark.parametrize("method", ["lasso", ORACLE_METHOD])
def test_unknown_method_is_an_argparse_error_listing_the_choices(tmp_path, capsys, method):
    with pytest.raises(SystemExit) as exc:
        run_cli("--library", FICUS / "library.csv", "--queries", FICUS / "queries.csv",
                "--method", method, "--output", tmp_path / "out.json")
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert f"invalid choice: '{method}'" in err
    assert all(name in err for name in (*DEPLOYABLE_METHODS, *METHOD_ALIASES))
    assert not (tmp_path / "out.json").exists()


def _bad_tables(tmp_path, kind):
    library = pd.read_csv(FICUS / "library.csv")
    queries = pd.read_csv(FICUS / "queries.csv")
    if kind == "overlap":
        queries.loc[0, "case_name"] = "candidate_006"
    elif kind == "duplicate":
        library.loc[1, "case_name"] = library.loc[0, "case_name"]
    elif kind == "missing column":
        queries = queries.drop(columns="norm_auc_rms_disp")
    elif kind == "non-finite":
        queries.loc[2, "early_velocity_ratio"] = np.nan
    elif kind == "non-positive scale":
        library.loc[3, "density_scale"] = 0.0
    lib, q = tmp_path / "L.csv", tmp_path / "Q.csv"
    library.to_csv(lib, index=False)
    queries.to_csv(q, index=False)
    return lib, q


@pytest.mark.parametrize(
    "kind, extra, message",
    [
        ("overlap", (), "also in the library"),
        ("duplicate", (), "duplicate case names"),
        ("missing column", (), "field 'norm_auc_rms_disp': missing column"),
        ("non-finite", (), "field 'early_velocity_ratio'"),
        ("non-positive scale", (), "field 'density_scale'"),
        (None, ("--k", "three"), "field '--k'"),
        (None, ("--alpha", "0.1"), "not an option of method 'response_knn'"),
        (None, ("--output", "LIB"), "would overwrite the --library input"),
    ],
)
def test_bad_input_exits_2_with_one_line(tmp_path, capsys, kind, extra, message):
    lib, q = _bad_tables(tmp_path, kind)
    opts = {"--method": "knn", "--output": str(tmp_path / "out.json")}
    it = iter(extra)
    opts.update({flag: value for flag, value in zip(it, it)})
    if opts["--output"] == "LIB":
        opts["--output"] = str(lib)
    args = ["--library", lib, "--queries", q]
    for flag, value in opts.items():
        args += [flag, value]
    assert run_cli(*args) == 2
    err = capsys.readouterr().err
    assert err.startswith("knockgs calibrate: error: ") and message in err
    assert err.count("\n") == 1
    assert not (tmp_path / "out.json").exists()


def test_module_entry_point(tmp_path):
    bad = tmp_path / "out.json"
    proc = subprocess.run(
        [sys.executable, "-m", "knockgs_core", "calibrate", "--library", str(FICUS / "library.csv"),
         "--queries", str(FICUS / "library.csv"), "--method", "nearest", "--output", str(bad)],
        capture_output=True, text=True, timeout=120,
    )
    assert proc.returncode == 2, proc.stderr
    assert proc.stderr.startswith("knockgs calibrate: error: ")
    assert "also in the library" in proc.stderr and "Traceback" not in proc.stderr

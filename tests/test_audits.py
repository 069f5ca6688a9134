"""The non-finite audit: numeric and mixed (number or word) table columns."""

from __future__ import annotations

import numpy as np
import pandas as pd

from knockgs_core.audits import audit_nonfinite


def _table(tmp_path, name, **cols):
    path = tmp_path / name
    pd.DataFrame(cols).to_csv(path, index=False)
    return path


def test_finite_tables_pass_and_inf_psnr_is_legitimate(tmp_path):
    ok = _table(tmp_path, "ok.csv", method=["a", "b"], psnr=[30.0, np.inf],
                observed_order=["0.875", "not in the asymptotic range"])
    r = audit_nonfinite([], [ok])
    assert r["passed"], r["problems"]
    assert r["tables_checked"] == 1


def test_nan_and_minus_inf_fail_in_numeric_and_mixed_columns(tmp_path):
    num = _table(tmp_path, "num.csv", method=["a", "b"], rmse=[1e-3, np.nan])
    mixed_nan = _table(tmp_path, "mixed_nan.csv", observed_order=["0.5", None])
    mixed_inf = _table(tmp_path, "mixed_inf.csv", observed_order=["not in the asymptotic range", "-inf"])
    r = audit_nonfinite([], [num, mixed_nan, mixed_inf])
    assert not r["passed"]
    text = "\n".join(r["problems"])
    assert "num.csv: NaN in ['rmse']" in text
    assert "mixed_nan.csv" in text and "mixed_inf.csv" in text and "observed_order" in text


def test_a_killed_writes_hidden_temporary_file_is_not_a_rollout(tmp_path):
    # a rollout streamed to a hidden temporary file (.NAME.tmpPID.parquet) until it is complete:
    # a job killed mid-rollout leaves it behind, truncated; the audit reads the rollouts only
    from knockgs_core.rollout import Rollout, write_rollout

    folder = tmp_path / "rollouts"
    folder.mkdir()
    X = np.zeros((2, 3, 3), dtype=np.float32)
    write_rollout(folder / "a.parquet", Rollout(positions=X, F=None, meta={"n_gs": 3}))
    (folder / ".b.parquet.tmp123.parquet").write_bytes(b"PAR1 truncated")
    r = audit_nonfinite([folder], [])
    assert r["passed"], r["problems"]
    (folder / "c.parquet").write_bytes(b"PAR1 truncated")  # a visible broken file is still a finding
    assert not audit_nonfinite([folder], [])["passed"]

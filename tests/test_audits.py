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

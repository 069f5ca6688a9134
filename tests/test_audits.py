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


def test_rollout_audits_on_threads_give_the_serial_verdict_in_the_same_order(tmp_path):
    # several good and broken rollouts (a NaN, a truncated file, a missing frame): the audits
    # read them on three threads and report the same problems, in the files' order
    import pyarrow as pa
    import pyarrow.parquet as pq

    from knockgs_core.audits import audit_missing_frames
    from knockgs_core.rollout import Rollout, write_rollout

    folder = tmp_path / "rollouts"
    folder.mkdir()
    rng = np.random.default_rng(3)
    meta = {"n_gs": 4, "n_fill": 0, "probe": {"export": {"n_frames": 3}}}
    for i in range(7):
        write_rollout(folder / f"r{i}.parquet", Rollout(positions=rng.normal(size=(3, 4, 3)), F=None, meta=meta))
    t = pq.read_table(folder / "r2.parquet")  # a NaN, written past the writer's own refusal
    x = t.column("x").to_numpy().copy()
    x[6] = np.nan
    pq.write_table(t.set_column(t.schema.get_field_index("x"), "x", pa.array(x)), folder / "r2.parquet")
    (folder / "r4.parquet").write_bytes((folder / "r4.parquet").read_bytes()[:40])
    t = pq.read_table(folder / "r5.parquet")
    pq.write_table(t.slice(0, 8), folder / "r5.parquet")  # frame 2 lost, the metadata kept
    for audit in (lambda w: audit_nonfinite([folder], [], workers=w), lambda w: audit_missing_frames([folder], workers=w)):
        serial, threaded = audit(1), audit(3)
        assert not serial["passed"] and serial["problems"]
        assert threaded == serial
    nonfinite = audit_nonfinite([folder], [], workers=3)["problems"]
    assert [p.split(":")[0].rsplit("/", 1)[-1] for p in nonfinite] == ["r2.parquet", "r4.parquet"]
    missing = audit_missing_frames([folder], workers=3)["problems"]
    assert [p.split(":")[0].rsplit("/", 1)[-1] for p in missing] == ["r4.parquet", "r5.parquet"]

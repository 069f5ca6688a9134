"""The discrepancy loop on a world case's folder and its score against the world's truth (the
floor loop's and the video world's benchmarks; no command)."""

from __future__ import annotations

import json
import math
import time
from pathlib import Path

import numpy as np


def run_and_score(case_dir, out, contract, particles, *, device) -> tuple[dict, dict]:
    """Run the loop (``run_discrepancy``, default settings) on the measured files that
    ``case_dir/truth.json`` names, at ``contract`` with ``particles`` on ``device``, into ``out``
    (a run whose result and predictions are there is read back, not repeated), and score it
    against the world's truth (``evaluate_case``, ``world_acceptance``). Returns (row, result):
    the row with ``accepted``, ``why``, ``seconds`` (NaN when read back) and ``points``."""
    from knockgs_core.discrepancy import evaluate_case, read_measured, run_discrepancy, world_acceptance, write_result

    out = Path(out)
    truth = json.loads((Path(case_dir) / "truth.json").read_text())
    m = read_measured(truth["measured_files"]["calib"])
    seconds = math.nan
    if not ((out / "result.json").is_file() and (out / "predictions.npz").is_file()):  # a run killed after it wrote them
        held = {truth["heldout_probe"]: read_measured(truth["measured_files"]["heldout"])}
        t0 = time.perf_counter()
        result = run_discrepancy(m, contract, particles, probe=truth["calibration_probe"],
                                 heldout_probes=[truth["heldout_probe"]], heldout_measured=held, device=device)
        seconds = time.perf_counter() - t0
        out.mkdir(parents=True, exist_ok=True)
        write_result(result, out)
    result = json.loads((out / "result.json").read_text())
    with np.load(out / "predictions.npz") as z:  # the predictions as the run's files hold them ({probe}/{stage})
        row = evaluate_case(result, dict(z), case_dir)
    ok, why = world_acceptance(row)
    row.update({"accepted": ok, "why": why, "seconds": seconds, "points": m.n_points})
    return row, result

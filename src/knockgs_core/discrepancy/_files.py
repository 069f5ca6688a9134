"""File-level entry points shared by the command line and the workflow (private)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from ..io import write_json, write_text
from ..errors import InputError
from ._loop import DiscrepancyResult, LibrarySource, LoopSettings, run_discrepancy
from ._measured import MEASUREMENT_META_FIELDS, MEASUREMENT_META_KEY, read_measured
from ._report import write_report
from ._resolution import check_floor_body, choose_resolution, qualify_verdict, read_floor_table, widen_by_floor_bias

__all__ = ["run_files", "evaluate_files", "audit_truth_separation"]


def _inside(path, folder) -> bool:
    try:
        Path(path).resolve().relative_to(Path(folder).resolve())
        return True
    except ValueError:
        return False


def library_source(rollouts: Sequence) -> LibrarySource:
    """The candidate library of the base calibration from its Probe-A rollout files.

    Members are named by their theta tag (``sE..._sR...``), not by their path, so the
    estimators' tie-breaks and fit order do not depend on where the files are kept; two
    files with one theta are an :class:`~knockgs_core.errors.InputError`.
    """
    from ..rollout import read_rollout_meta, theta_tag

    thetas = [read_rollout_meta(p)["theta"] for p in rollouts]
    names = tuple(theta_tag(t) for t in thetas)
    seen: dict[str, str] = {}
    for name, path in zip(names, rollouts):
        if name in seen:
            raise InputError(path, "metadata.knockgs.theta", f"theta {name} is also the theta of {seen[name]}")
        seen[name] = str(path)
    paths = tuple(str(p) for p in rollouts)
    return LibrarySource(theta=np.array(thetas, dtype=float), names=names, rollouts=paths)


def _check_measurement_use(m, contract, probe: str | None) -> None:
    """A measurement's metadata (object, profile, probe; when present) against its use."""
    for key, want in (("object", contract.name), ("profile", contract.profile), ("probe", probe)):
        got = m.meta.get(key)
        if want is not None and got is not None and got != want:
            raise InputError(m.source, f"metadata.{key}", f"the file says '{got}', it is used as '{want}'")


def _read_json(path, field: str):
    try:
        return json.loads(Path(path).read_text())
    except FileNotFoundError:
        raise InputError(path, field, "no such file") from None
    except (OSError, ValueError) as exc:
        raise InputError(path, field, f"not a readable JSON file ({exc})") from None


def _read_npz(path, field: str) -> dict:
    try:
        with np.load(path, allow_pickle=False) as z:
            return {k: z[k] for k in z.files}
    except FileNotFoundError:
        raise InputError(path, field, "no such file") from None
    except Exception as exc:  # BadZipFile, EOFError, ValueError (object arrays), OSError
        raise InputError(path, field, f"not a readable .npz file ({type(exc).__name__}: {exc})") from None


def run_files(
    object_name: str,
    profile: str,
    measured,
    out_dir,
    *,
    particles=None,
    probe: str | None = None,
    heldout_probes: Sequence[str] = (),
    heldout_measured: dict | None = None,
    library_rollouts: Sequence = (),
    settings: LoopSettings = LoopSettings(),
    device: str | None = None,
    deterministic: bool = False,
    config_dir=None,
    progress: Callable[[str], None] | None = None,
    n_grid: int | None = None,
    floor_table=None,
    smallest_effect: float = 0.2,
) -> DiscrepancyResult:
    """Load the contract and particles (``particles``: a ``.npz`` from ``knockgs asset``,
    else the asset is built), read ``measured`` (and ``heldout_measured``: probe -> file),
    run :func:`run_discrepancy` (library base calibration when ``library_rollouts`` are
    given; ``device`` and ``deterministic``: its rollouts') and write the report into
    ``out_dir``. Every file read is listed in ``result.inputs``. ``n_grid``: the model's grid, the
    contract at that resolution (:func:`~knockgs_core.contract.at_resolution`; particles and
    library rollouts made at another grid are refused by its hash). ``floor_table``: a floor
    study's CSV: without ``n_grid`` the loop runs at its coarsest level within half of
    ``smallest_effect`` (a fraction of the response) of the finite-element reference, else at
    its finest; with ``n_grid``, at that level of the table (which must have it); either way it
    says which and why (``result.resolution``, the report's "Resolution") and its theta interval
    is widened by what that level's floor can do to theta (:func:`._resolution.widen_by_floor_bias`;
    the widening in log theta is ``result.resolution["theta_widening_log"]``)."""
    from ..io import check_input, check_outputs
    from ..contract import at_resolution, load_contract
    from ..rollout import check_rollout_meta, read_rollout_meta

    contract = load_contract(object_name, profile, config_dir=config_dir)
    choice = None
    if floor_table is not None:
        check_input(floor_table, "--floor-table")
        choice = choose_resolution(read_floor_table(floor_table), smallest_effect=smallest_effect, n_grid=n_grid,
                                   source=floor_table)
        n_grid = choice["n_grid"]
    if n_grid is not None and int(n_grid) != contract.sim.n_grid:   # at its own grid the contract is itself
        contract = at_resolution(contract, n_grid)
    held_files = dict(heldout_measured or {})
    check_outputs({"--output": out_dir},
                  {"--object": contract.source, "--measured": measured, "--particles": particles, "--floor-table": floor_table,
                   "--heldout-measured": list(held_files.values()), "--library-rollout": list(library_rollouts)},
                  directories={"--output": ("report.md", "result.json", "predictions.npz", "residuals_*.png")})
    m = read_measured(measured)
    _check_measurement_use(m, contract, probe)
    held = {}
    for name, path in held_files.items():
        held[name] = read_measured(path)
        _check_measurement_use(held[name], contract, name)
    if particles:
        from ..assets import load_particles

        ps = load_particles(particles, contract=contract)
    else:
        from ..assets import build_asset

        ps = build_asset(contract).particles
    if choice is not None:
        check_floor_body(choice, contract, ps)
    inputs = [str(measured)] + ([str(particles)] if particles else []) + ([str(floor_table)] if choice else [])
    inputs += [str(p) for p in held_files.values()]
    library_probe = probe or m.meta.get("probe") or contract.roles.get("calibration")
    for path in library_rollouts:
        check_rollout_meta(path, read_rollout_meta(path), object=contract.name, profile=contract.profile,
                           contract_hash=contract.hash, probe=library_probe, n_particles=len(ps))
    library = library_source(library_rollouts) if library_rollouts else None
    inputs += [str(p) for p in library_rollouts]
    result = run_discrepancy(m, contract, ps, probe=probe, heldout_probes=heldout_probes, heldout_measured=held,
                             library=library, settings=settings, device=device,
                             deterministic=deterministic, progress=progress)
    result.inputs = inputs
    if choice is not None:
        if result.theta_interval:
            per_response = (result.theta_uncertainty or {}).get("theta_per_response_log")
            result.theta_interval, choice["theta_widening_log"] = widen_by_floor_bias(result.theta_interval, choice,
                                                                                  per_response)
        result.verdict = qualify_verdict(result.verdict, result.identified, choice)
    result.resolution = choice
    write_report(result, out_dir)
    return result


def evaluate_files(run_dir, truth_dir, output, markdown=None) -> dict:
    """Score a run folder against a case's truth folder; write the row as JSON (and, with
    ``markdown``, a short evaluation page: planted vs found, errors against the truth)."""
    from ._scoring import acceptance, evaluate_case

    from ..io import check_outputs

    run_dir, truth_dir = Path(run_dir), Path(truth_dir)
    reads = {"--run-dir": [run_dir / "result.json", run_dir / "predictions.npz"],
             "--truth-dir": [truth_dir / "truth.json", truth_dir / "clean.npz"]}
    check_outputs({"--output": output, "--markdown": markdown}, reads)
    result = _read_json(run_dir / "result.json", "--run-dir")
    preds = _read_npz(run_dir / "predictions.npz", "--run-dir")
    _read_json(truth_dir / "truth.json", "--truth-dir")  # readable before the scoring reads them
    _read_npz(truth_dir / "clean.npz", "--truth-dir")
    try:
        row = evaluate_case(result, preds, truth_dir)
    except (KeyError, TypeError) as exc:
        raise InputError(run_dir, "--run-dir", f"result.json or predictions.npz lacks {exc} "
                         "(not the output of `knockgs discrepancy run`?)") from None
    write_json(output, row)
    if markdown is not None:
        ok, why = acceptance(row)
        g = lambda v: f"{v:.4g}" if isinstance(v, float) else str(v)  # noqa: E731
        lines = [
            f"# Evaluation of case {row['case']} against its truth",
            "",
            f"- planted: {row['planted_effect']}"
            + (f" ({row['parameter']} = {g(row['planted_value'])})" if row["parameter"] else ""),
            f"- found: {row['identified_effect']}"
            + (f" ({row['parameter']} = {g(row['estimated_value'])})" if row["estimated_value"] != "" else "")
            + f"; ranked first in round 1: {row['first_ranked']}; residual left unexplained: {row['unexplained']}",
            f"- theta: true {row['theta_true']}, before {row['theta_before']} ({row['theta_error_before_pct']:.2f} % error), "
            f"after {row['theta_after']} ({row['theta_error_after_pct']:.2f} % error)",
            f"- acceptance: {'pass' if ok else 'FAIL'} ({why})",
            "",
            "Trajectory RMSE [m] against the clean truth (Gaussian particles, all frames):",
            "",
            "| probe | before | theta refit | after | before / after |",
            "|---|---|---|---|---|",
        ]
        for role, name in (("calib", "calibration"), ("heldout", "held-out (never used in the loop)")):
            b, r, a = row[f"{role}_traj_rmse_before"], row[f"{role}_traj_rmse_refit"], row[f"{role}_traj_rmse_after"]
            lines.append(f"| {name} | {b:.4g} | {r:.4g} | {a:.4g} | {b / max(a, 1e-30):.3g} |")
        write_text(markdown, "\n".join(lines) + "\n")
    return row


def audit_truth_separation(results: Sequence, measured_files: Sequence, truth_dirs: Sequence,
                           declared_inputs: dict | None = None) -> dict:
    """Verdict that the loop never saw the truth: no run read a file under a truth folder
    (``inputs`` recorded in each ``result.json``, and the workflow's declared inputs of the
    run jobs, ``declared_inputs``: case -> files), and no measured file carries metadata
    beyond :data:`MEASUREMENT_META_FIELDS` (no planted effect, no theta)."""
    import pyarrow.parquet as pq

    problems = []
    for res in results:
        doc = json.loads(Path(res).read_text())
        for p in doc.get("inputs", []):
            for t in truth_dirs:
                if _inside(p, t):
                    problems.append(f"{res}: the run read {p} under the truth folder {t}")
        if not doc.get("inputs"):
            problems.append(f"{res}: records no inputs")
    for case, files in (declared_inputs or {}).items():
        for p in files:
            for t in truth_dirs:
                if _inside(p, t):
                    problems.append(f"run job of {case} declares the truth file {p} as input")
    for f in measured_files:
        for t in truth_dirs:
            if _inside(f, t):
                problems.append(f"measured file {f} lies under the truth folder {t}")
        if str(f).endswith(".parquet"):
            md = pq.read_schema(f).metadata or {}
            extra = set(md) - {MEASUREMENT_META_KEY, b"pandas"}
            if extra:
                problems.append(f"{f}: unexpected metadata keys {sorted(k.decode() for k in extra)}")
            if MEASUREMENT_META_KEY in md:
                bad = set(json.loads(md[MEASUREMENT_META_KEY])) - set(MEASUREMENT_META_FIELDS)
                if bad:
                    problems.append(f"{f}: metadata fields {sorted(bad)} beyond {list(MEASUREMENT_META_FIELDS)}")
        try:
            read_measured(f)
        except InputError as exc:
            problems.append(f"{f}: {exc}")
    checked = {"results": len(results), "measured_files": len(measured_files), "truth_dirs": [str(t) for t in truth_dirs]}
    return {"passed": not problems, "problems": problems, "checked": checked}

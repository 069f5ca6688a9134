"""Audits of a workflow run; each returns a JSON-ready verdict ``{"passed": bool, ...}``.

- leakage: no deployable estimator read a Probe-B file, a target label or anything but the
  candidate library and the Probe-A query table; the query table carries no labels; no
  target is a library candidate; library rollouts are Probe-A rollouts of candidates.
- non-finite: every rollout and table is finite (rollouts read with the one long-format
  reader, :mod:`knockgs_core.io`, which also reports a malformed file).
- missing frames: every rollout holds every exported frame of every particle (a truncated
  or unreadable file is a failed verdict naming it, not a crash).
- rollout metadata: every cached rollout (and its deformation-gradient file) is the rollout
  its place in the path grammar says it is: object, profile, contract hash, theta, probe,
  particle and frame counts (a rollout copied over another's path is caught).
- duplicates: no duplicate case names or parameter pairs among candidates and targets.
- completion: every expected output exists and every main table has every method.
"""

from __future__ import annotations

import json
import os
import re
import shlex
from pathlib import Path
from typing import Iterable, Mapping, Sequence

import numpy as np
import pandas as pd
import pyarrow.parquet as pq

from .io import POSITION_COLUMNS, check_rollout_meta, read_long_values, read_metadata
from .io import ordered_map
from .descriptors import FEATURE_NAMES
from .errors import InputError

__all__ = ["audit_leakage", "audit_nonfinite", "audit_missing_frames", "audit_rollout_metadata", "rollout_expectations",
           "audit_duplicates", "audit_completion"]

LABEL_COLUMNS = ("E_scale", "density_scale", "E_true", "rho_true")
#: schema-metadata key of a rollout file (see :mod:`knockgs_core.rollout`)
_META_KEY = b"knockgs"


def _rollout_meta(path) -> dict:
    meta = read_metadata(path, _META_KEY)
    if meta is None:
        raise InputError(path, "metadata.knockgs", "missing: not a KnockGS rollout")
    return meta


def audit_leakage(
    estimate_files: Iterable,
    *,
    calibration_probes: Mapping[str, str],
    candidates: pd.DataFrame,
    targets: pd.DataFrame,
    library_rollouts: Iterable = (),
    sensitivity_grids: Iterable = (),
    frozen: Mapping | None = None,
    passive_library_rollouts: Iterable = (),
) -> dict:
    """Leakage from recorded inputs. ``calibration_probes``: object -> Probe-A name.
    Estimate files live at ``.../estimates/{object}/{split}/{method}.json``.
    ``sensitivity_grids``: k x alpha tables (``sensitivity_k_alpha_{object}.csv``), whose
    held-out column must reach no selection: the row marked ``frozen`` is the configuration
    ``frozen`` (the config's local-ridge k and alpha), and ``loo_best`` marks the lowest
    leave-one-out error, whatever the held-out errors. An estimate of the passive route (under
    a ``passive`` folder) reads only passive descriptor tables, an active one none;
    ``passive_library_rollouts`` must all be candidates under the passive protocol."""
    from .experiments import PASSIVE_PROBE

    problems: list[str] = []
    checked = 0
    for f in estimate_files:
        f = Path(f)
        doc = json.loads(f.read_text())
        if not doc.get("deployable", False):
            continue  # the oracle is evaluation-only by construction
        checked += 1
        obj = f.parent.parent.name
        inputs = [str(x) for x in doc.get("rule_inputs", [])] or [str(x) for x in doc.get("inputs", {}).values()]
        if not inputs:
            problems.append(f"{f}: no recorded inputs")
        for inp in inputs:
            name = Path(inp).name
            allowed = name == "library.csv" or (name.startswith("queries_") and name.endswith(".csv"))
            if not allowed:
                problems.append(f"{f}: deployable estimator read '{inp}' (only library.csv and queries_*.csv are allowed)")
            if "/eval/" in inp or "/rollouts/" in inp or "targets" in name or "ground_truth" in name:
                problems.append(f"{f}: input '{inp}' is a rollout or label file")
            if ("passive" in f.parts) != ("passive" in Path(inp).parts):
                problems.append(f"{f}: input '{inp}' belongs to the other route (passive vs Probe A)")
        for inp in inputs:
            if Path(inp).name.startswith("queries_") and Path(inp).exists():
                cols = set(pd.read_csv(inp, nrows=1).columns)
                bad = cols & set(LABEL_COLUMNS)
                extra = cols - {"case_name", *FEATURE_NAMES}
                if bad:
                    problems.append(f"{inp}: query table carries label columns {sorted(bad)}")
                if extra - bad:
                    problems.append(f"{inp}: query table carries unexpected columns {sorted(extra - bad)}")
        _ = obj
    cand_pairs = {(round(a, 9), round(b, 9)) for a, b in zip(candidates.E_scale, candidates.density_scale)}
    for r in targets.itertuples(index=False):
        if (round(r.E_scale, 9), round(r.density_scale, 9)) in cand_pairs:
            problems.append(f"target {r.case_name} ({r.E_scale}, {r.density_scale}) is a library candidate")
    n_lib = 0
    for f in library_rollouts:
        n_lib += 1
        md = _rollout_meta(f)
        want = calibration_probes.get(md["object"])
        if md["probe"]["name"] != want:
            problems.append(f"{f}: library rollout under probe '{md['probe']['name']}', not Probe A '{want}'")
        if (round(md["theta"][0], 6), round(md["theta"][1], 6)) not in {(round(a, 6), round(b, 6)) for a, b in cand_pairs}:
            problems.append(f"{f}: library rollout at theta {md['theta']} is not a candidate")
    for f in passive_library_rollouts:
        n_lib += 1
        md = _rollout_meta(f)
        if md["probe"]["name"] != PASSIVE_PROBE:
            problems.append(f"{f}: passive library rollout under probe '{md['probe']['name']}', not '{PASSIVE_PROBE}'")
        if any(abs(float(x)) > 0 for x in md["probe"]["force"]):
            problems.append(f"{f}: passive library rollout with a known force {md['probe']['force']}")
        if (round(md["theta"][0], 6), round(md["theta"][1], 6)) not in {(round(a, 6), round(b, 6)) for a, b in cand_pairs}:
            problems.append(f"{f}: passive library rollout at theta {md['theta']} is not a candidate")
    n_grids = 0
    for f in sensitivity_grids:
        n_grids += 1
        g = pd.read_csv(f)
        fz = g[g["frozen"].astype(bool)]
        if len(fz) != 1:
            problems.append(f"{f}: {len(fz)} rows marked frozen (expected 1)")
        elif frozen is not None and (int(fz["k"].iloc[0]) != int(frozen.get("k", 10))
                                     or not np.isclose(float(fz["alpha"].iloc[0]), float(frozen.get("alpha", 1e-3)))):
            problems.append(f"{f}: the frozen row (k = {fz['k'].iloc[0]}, alpha = {fz['alpha'].iloc[0]}) is not the "
                            f"configuration {dict(frozen)}")
        best = g[g["loo_best"].astype(bool)]
        if len(best) != 1 or float(best["loo_joint_error_pct"].iloc[0]) != float(g["loo_joint_error_pct"].min()):
            problems.append(f"{f}: loo_best does not mark the lowest leave-one-out error")
    return {"passed": not problems, "deployable_estimates_checked": checked, "library_rollouts_checked": n_lib,
            "sensitivity_grids_checked": n_grids, "problems": problems}


def _rollout_files(dirs: Sequence) -> list[Path]:
    """The rollout files under ``dirs``: not the deformation gradients (``*.F.parquet``), and not
    the hidden temporary file of a write a killed job left behind (``.NAME.tmpPID.parquet``)."""
    files: list[Path] = []
    for d in dirs:
        files += sorted(p for p in Path(d).rglob("*.parquet") if not p.name.endswith(".F.parquet")
                        and not p.name.startswith("."))
    return files


def audit_nonfinite(rollout_dirs: Sequence, tables: Iterable, *, workers: int = 1) -> dict:
    """Every rollout coordinate and every numeric table cell is finite. The rollouts are read
    by ``workers`` threads (:func:`knockgs_core.io.ordered_map`; the same verdict for
    any count)."""
    files = _rollout_files(rollout_dirs)

    def rollout_problem(f) -> str | None:
        try:  # the long-format reader refuses non-finite values, naming the column
            read_long_values(f, POSITION_COLUMNS)
        except InputError as exc:
            return f"{f}: non-finite {exc.field}" if "non-finite" in exc.message else f"{f}: {exc.message}"
        return None

    problems = [msg for msg in ordered_map(rollout_problem, files, workers=workers) if msg is not None]
    n_tables = 0
    for f in tables:
        n_tables += 1
        try:
            df = pd.read_csv(f)
        except Exception as exc:  # an empty, truncated or binary file is a finding, not a crash
            problems.append(f"{f}: not a readable CSV table ({type(exc).__name__}: {' '.join(str(exc).split())})")
            continue
        num = df.select_dtypes(include=[np.number])
        vals = num.to_numpy(dtype=float)
        # +inf PSNR (identical frames) is a legitimate value; NaN and -inf are not
        bad = np.isnan(vals) | np.isneginf(vals)
        if bad.any():
            cols = sorted({num.columns[j] for j in np.nonzero(bad)[1]})
            problems.append(f"{f}: NaN in {cols}")
        # text columns may mix numbers and words (e.g. "not in the asymptotic range"): an
        # empty cell or a "-inf" there is still a missing or broken number
        text = df.select_dtypes(exclude=[np.number, "bool"])
        as_number = text.apply(pd.to_numeric, errors="coerce").to_numpy(dtype=float)
        bad = text.isna().to_numpy(dtype=bool) | np.isneginf(as_number)
        if bad.any():
            cols = sorted({text.columns[j] for j in np.nonzero(bad)[1]})
            problems.append(f"{f}: NaN or empty cells in {cols}")
    return {"passed": not problems, "rollouts_checked": len(files), "tables_checked": n_tables, "problems": problems}


def audit_missing_frames(rollout_dirs: Sequence, *, workers: int = 1) -> dict:
    """Every rollout has rows for all frames x particles and as many frames as its probe exports.
    The rollouts are read by ``workers`` threads (the same verdict for any count)."""
    files = _rollout_files(rollout_dirs)

    def frames_problem(f) -> str | None:
        try:
            md = _rollout_meta(f)
            n_frames = md["probe"]["export"]["n_frames"]
            n = md["n_gs"] + md["n_fill"]
        except InputError as exc:
            return f"{f}: {exc.field}: {exc.message}"
        except (KeyError, TypeError):
            return f"{f}: metadata.knockgs: no probe.export.n_frames, n_gs or n_fill"
        try:  # the frame column a row group at a time: its rows per frame, not the whole column in memory
            with pq.ParquetFile(f) as pf:
                counts = np.zeros(n_frames, dtype=np.int64)
                for g in range(pf.metadata.num_row_groups):
                    frames = pf.read_row_group(g, columns=["frame"]).column("frame").to_numpy()
                    if frames.size and frames.min() < 0:
                        counts = np.zeros(0, dtype=np.int64)
                        break
                    got = np.bincount(frames, minlength=counts.size)
                    counts = np.pad(counts, (0, got.size - counts.size)) + got
        except Exception as exc:  # truncated or corrupted: ArrowInvalid, OSError
            return f"{f}: unreadable ({type(exc).__name__}: {' '.join(str(exc).split())})"
        if len(counts) != n_frames or np.any(counts != n):
            return f"{f}: expected {n_frames} frames x {n} particles, found frame counts {counts.tolist()[:8]}..."
        return None

    problems = [msg for msg in ordered_map(frames_problem, files, workers=workers) if msg is not None]
    return {"passed": not problems, "rollouts_checked": len(files), "problems": problems}


def _theta_of_tag(tag: str) -> tuple[float, float] | None:
    m = re.fullmatch(r"sE([0-9.]+)_sR([0-9.]+)", tag)
    return (float(m.group(1)), float(m.group(2))) if m else None


def _expected_from_path(f: Path, root: Path, obj: Mapping) -> dict:
    """What the path grammar says a cached rollout is (see the Snakefile):
    ``lib/chunk*/{theta}.parquet`` (Probe A), ``eval/{theta}/{probe}.parquet`` or
    ``diag/{split}/{set}/{theta}__{probe}.parquet`` (that probe), ``passive/{job}/{theta}.parquet``
    (the passive protocol, exported like Probe A)."""
    from .experiments import PASSIVE_PROBE

    rel = f.relative_to(root).parts
    want = {"object": obj["object"], "profile": obj.get("profile"), "contract_hash": obj.get("contract_hash"),
            "n_particles": obj.get("n_particles")}
    probe, frames_of = None, None
    if len(rel) == 3 and rel[0] == "lib":
        want["theta"], probe = _theta_of_tag(rel[2].removesuffix(".parquet")), obj.get("calibration_probe")
    elif len(rel) == 3 and rel[0] == "eval":
        want["theta"], probe = _theta_of_tag(rel[1]), rel[2].removesuffix(".parquet")
    elif len(rel) == 4 and rel[0] == "diag":
        tag, _, probe = rel[3].removesuffix(".parquet").partition("__")
        want["theta"] = _theta_of_tag(tag)
    elif len(rel) == 3 and rel[0] == "passive":
        want["theta"], probe = _theta_of_tag(rel[2].removesuffix(".parquet")), PASSIVE_PROBE
        frames_of = obj.get("calibration_probe")
    want["probe"] = probe
    want["n_frames"] = obj.get("n_frames", {}).get(frames_of or probe)
    return want


def audit_rollout_metadata(objects: Mapping[str, Mapping]) -> dict:
    """Every cached rollout is the one its path names; every F file belongs to its rollout.

    ``objects``: object -> {``rollout_dir`` (``P/rollouts/{object}``), ``object``,
    ``profile``, ``contract_hash``, ``calibration_probe``, ``n_particles``, ``n_frames``
    (probe -> exported frames)}. The rollout's metadata must match what its place in the
    path grammar says (object, profile, contract hash, theta, probe, particle and frame
    counts); its ``.F.parquet`` sibling, when present, must carry the same object, profile,
    contract hash, theta, probe and n_gs, and n_frames x n_gs rows. Only metadata and
    Parquet footers are read. A mismatch or an unreadable file is a problem naming the file.
    """
    problems: list[str] = []
    n_files = 0
    for name, obj in objects.items():
        root = Path(obj["rollout_dir"])
        obj = {"object": name, **obj}
        for f in _rollout_files([root]):
            n_files += 1
            want = _expected_from_path(f, root, obj)
            md = _check_cached(f, want, problems)
            F = f.with_name(f.name.removesuffix(".parquet") + ".F.parquet")
            if F.exists():
                n_files += 1
                n_gs = md.get("n_gs") if isinstance(md, dict) and isinstance(md.get("n_gs"), int) else None
                f_want = {k: v for k, v in want.items() if k not in ("n_particles", "n_frames")}
                _check_cached(F, {**f_want, "n_gs": n_gs}, problems,  # n_rows 0: unknown, not compared
                              n_rows=(want.get("n_frames") or 0) * n_gs if n_gs is not None else 0)
    return {"passed": not problems, "files_checked": n_files, "problems": problems}


def rollout_expectations(objects: Sequence[str], profile: str, rollout_dirs: Sequence, particle_files: Sequence,
                         config_dir=None) -> dict:
    """The ``objects`` argument of :func:`audit_rollout_metadata` for a workflow run: each
    object's contract at ``profile`` (hash, calibration probe, exported frames per probe)
    and its particle count (from its particle file)."""
    from .assets import load_particles
    from .contract import load_contract

    out = {}
    for name, folder, particles in zip(objects, rollout_dirs, particle_files):
        c = load_contract(name, profile, config_dir=config_dir)
        out[name] = {"rollout_dir": str(folder), "profile": c.profile, "contract_hash": c.hash,
                     "calibration_probe": c.roles["calibration"], "n_particles": len(load_particles(particles)),
                     "n_frames": {k: probe.export.n_frames for k, probe in c.probes.items()}}
    return out


def _check_cached(f: Path, want: dict, problems: list, n_rows: int | None = None) -> dict | None:
    """One cached file against what its path says (``want``) and its row count (the
    rollout's frames x particles, or ``n_rows``): its metadata, or None when it failed."""
    try:
        md = _rollout_meta(f)
        if want.get("theta", 0) is None:
            raise InputError(f, "path", "no theta tag sE..._sR... where the path grammar has one")
        check_rollout_meta(f, md, **want)
        rows = pq.ParquetFile(f).metadata.num_rows
        if n_rows is None:
            n_frames, n = md["probe"]["export"]["n_frames"], md["n_gs"] + md["n_fill"]
            if rows != n_frames * n:
                raise InputError(f, "rows", f"{rows} rows, the metadata says {n_frames} frames x {n} particles")
        elif n_rows and rows != n_rows:
            raise InputError(f, "rows", f"{rows} rows, its rollout has {n_rows} (frames x GS particles)")
        return md
    except InputError as exc:
        problems.append(f"{exc.source}: {exc.field}: {exc.message}")
    except Exception as exc:  # a truncated footer, malformed metadata: a finding, not a crash
        problems.append(f"{f}: unreadable ({type(exc).__name__}: {' '.join(str(exc).split())})")
    return None


def audit_duplicates(candidates: pd.DataFrame, targets: pd.DataFrame, library_tables: Iterable = ()) -> dict:
    """No duplicate case names or parameter pairs among candidates, targets and libraries."""
    problems = []
    for name, df in [("candidates", candidates), ("targets", targets)]:
        if df.case_name.duplicated().any():
            problems.append(f"{name}: duplicate case names {sorted(df.case_name[df.case_name.duplicated()])}")
        pairs = df[["E_scale", "density_scale"]].round(9)
        if pairs.duplicated().any():
            problems.append(f"{name}: duplicate parameter pairs {pairs[pairs.duplicated()].values.tolist()}")
    for f in library_tables:
        lib = pd.read_csv(f)
        if lib.case_name.duplicated().any() or lib[["E_scale", "density_scale"]].round(9).duplicated().any():
            problems.append(f"{f}: duplicate cases")
        if len(lib) != len(candidates):
            problems.append(f"{f}: {len(lib)} rows for {len(candidates)} candidates")
    return {"passed": not problems, "candidates": len(candidates), "targets": len(targets), "problems": problems}


def stale_staging_folders(root) -> list[str]:
    """The staging folders (``.NAME.partial``, :func:`knockgs_core.io.staging_folder`) under
    ``root``, sorted; their contents are not searched. A job builds its output folder in one and
    renames it into place when whole; a job stopped by SIGKILL leaves it, and only that job's
    next attempt removes it."""
    found = []
    for top, dirs, _ in os.walk(root):
        for d in list(dirs):
            if d.startswith(".") and d.endswith(".partial"):
                found.append(os.path.join(top, d))
                dirs.remove(d)
    return sorted(found)


def audit_completion(expected: Iterable, main_tables: Iterable = (), methods: Sequence[str] = (), *,
                     results=None) -> dict:
    """Every expected output exists (non-empty) and every main table lists every method.

    With ``results`` (the profile's results folder) the verdict also lists, as
    ``stale_staging``, the staging folders left under it (:func:`stale_staging_folders`). The
    audit runs once every job of the run has ended, so no job owns them any more: a job
    stopped by SIGKILL left each, and a job that is not run again (its outputs no longer
    asked for) never removes it. They are reported, with ``warnings``, and do not fail the
    audit: no output is read from them, they only hold disk space."""
    expected = [str(e) for e in expected]
    missing = [e for e in expected if not Path(e).exists() or Path(e).stat().st_size == 0]
    problems = [f"missing output {m}" for m in missing]
    for f in main_tables:
        got = set(pd.read_csv(f)["method"])
        lost = [m for m in methods if m not in got]
        if lost:
            problems.append(f"{f}: methods missing {lost}")
    verdict = {"passed": not problems, "expected": len(expected), "problems": problems}
    if results is not None:
        stale = stale_staging_folders(results)
        verdict["stale_staging"] = stale
        verdict["warnings"] = [f"{len(stale)} staging folder(s) of jobs stopped before their end, no output read "
                               f"from them; remove them with: rm -r {' '.join(shlex.quote(f) for f in stale)}"] if stale else []
    return verdict

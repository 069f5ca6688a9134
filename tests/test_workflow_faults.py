"""Workflow faults on the ci profile (issue 17): an interrupted run (Ctrl-C, SIGTERM or SIGKILL of
the whole process group) resumes to byte-identical tables, and the audits catch a cached
rollout that was swapped for another or truncated behind Snakemake's back, with a verdict
naming the file (not a crash). One object (Pillow), the descriptor table of a candidate library
of 12 (the first rows of config/candidates.csv): the asset job and two library jobs of six,
enough to stop one job while the other writes, at a fifth of the full library's cost.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow.parquet as pq
import pytest

from _workflow import (CI_RUN_CONFIG, LIBRARY_TABLE, N_LIBRARY, library_run, scratch_copy, small_library, snakemake,
                       snakemake_env)

from knockgs_core.audits import audit_missing_frames, audit_nonfinite, audit_rollout_metadata, rollout_expectations

P = "results/ci"
TABLE = LIBRARY_TABLE
ARGS = ("--cores", "2", *CI_RUN_CONFIG, "--")  # the shared small library's settings (tests/_workflow.py)
N_CANDIDATES = N_LIBRARY


def _workflow(dest: Path) -> Path:
    """A scratch copy of the workflow whose candidate library is the first N_CANDIDATES rows."""
    return small_library(scratch_copy(dest), N_CANDIDATES)


def _start(work: Path, *extra: str) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "snakemake", *extra, *ARGS, TABLE], cwd=work, start_new_session=True,
                            env=snakemake_env(),
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)


@pytest.fixture
def reference(tmp_path_factory):
    """An uninterrupted run: the table and the rollout cache it was computed from (the shared
    small-library run, read only)."""
    work = library_run(tmp_path_factory)
    assert len(pd.read_csv(work / TABLE)) == N_CANDIDATES
    return work


def _interrupt(work: Path, sig: int) -> bool:
    """Start the run, signal it once library rollouts are being written; True when the signal
    stopped it before the table (False: the run had already got past the point of no return,
    which a loaded machine's scheduling can cause: the attempt proves nothing)."""
    proc = _start(work)
    lib = work / P / "rollouts/pillow/lib"
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline and proc.poll() is None:
        if len(list(lib.glob("*chunk*/*.F.parquet"))) >= 3:  # library jobs under way (staged), some rollouts written
            break
        time.sleep(0.05)
    assert proc.poll() is None, "the run ended before it could be interrupted"
    # Ctrl-C reaches the whole foreground group; SIGTERM: a batch system's time limit or cancel
    # (Python's default: the job runs no clean-up; Snakemake records the lost jobs, removes
    # their outputs and stops); SIGKILL: a power cut
    os.killpg(proc.pid, sig)
    proc.communicate(timeout=120)
    return not (work / TABLE).exists()


def _interrupt_and_resume(work: Path, sig: int, *, recorded: bool = False) -> subprocess.CompletedProcess:
    """Interrupt a run (:func:`_interrupt`) and resume it. ``recorded``: then remove
    Snakemake's marks of the jobs under way, as though it had recorded them as finished: the
    state a Snakemake leaves when it is killed after it records a lost job and before it
    removes the job's output (it does both on a SIGTERM; seen on a GPU node whose run got a
    SIGTERM and a SIGKILL moments later). A resumed run then trusts any output folder it
    finds, so a job's folder must not exist before the job has written all of it."""
    for _ in range(3):
        if _interrupt(work, sig):
            break
        shutil.rmtree(work / P, ignore_errors=True)
        shutil.rmtree(work / ".snakemake", ignore_errors=True)
    assert not (work / TABLE).exists(), "three runs finished before the signal stopped them"
    if recorded:
        marks = work / ".snakemake" / "incomplete"
        assert any(marks.iterdir()), "no job was under way at the signal"
        shutil.rmtree(marks)
    if sig == signal.SIGKILL:  # a killed Snakemake leaves its lock: the documented first step is --unlock
        unlock = snakemake(work, "--unlock", *ARGS, TABLE)
        assert unlock.returncode == 0, unlock.stderr[-2000:]
    return snakemake(work, "--rerun-incomplete", *ARGS, TABLE)


@pytest.mark.slow
@pytest.mark.parametrize(("sig", "recorded"), [(signal.SIGINT, False), (signal.SIGTERM, False), (signal.SIGKILL, False),
                                              (signal.SIGKILL, True)],
                         ids=["SIGINT", "SIGTERM", "SIGKILL", "SIGKILL-jobs-recorded"])
def test_an_interrupted_run_resumes_to_the_same_bytes(reference, tmp_path, sig, recorded):
    work = _workflow(tmp_path / "wf")
    out = _interrupt_and_resume(work, sig, recorded=recorded)
    assert out.returncode == 0, out.stderr[-3000:]
    assert (work / TABLE).read_bytes() == (reference / TABLE).read_bytes()
    # no temporary file of the atomic writer and no staging folder is left anywhere in the results
    assert [p for p in (work / P).rglob("*") if ".tmp" in p.name or p.name.endswith(".partial")] == []


def _cache_copy(reference: Path, dest: Path) -> Path:
    shutil.copytree(reference / P, dest / P, ignore=shutil.ignore_patterns("benchmarks"))
    shutil.copytree(reference / "config", dest / "config")
    return dest


def _expect(work: Path) -> dict:
    return rollout_expectations(["pillow"], "ci", [work / P / "rollouts/pillow"], [work / P / "assets/pillow.particles.npz"],
                                config_dir=work / "config")


@pytest.mark.slow
def test_the_rollout_cache_of_a_clean_run_passes_the_audits(reference):
    verdict = audit_rollout_metadata(_expect(reference))
    assert verdict["passed"], verdict["problems"][:3]
    assert verdict["files_checked"] == 2 * N_CANDIDATES  # the library rollouts and their F files
    assert audit_missing_frames([reference / P / "rollouts/pillow"])["passed"]


@pytest.mark.slow
def test_another_candidates_rollout_copied_over_a_library_path_is_caught(reference, tmp_path):
    work = _cache_copy(reference, tmp_path)
    files = sorted((work / P / "rollouts/pillow/lib/chunk0").glob("*[0-9].parquet"))
    victim = files[1]
    stat = victim.stat()
    shutil.copy(files[0], victim)  # a valid rollout, of another theta
    os.utime(victim, ns=(stat.st_atime_ns, stat.st_mtime_ns))  # Snakemake sees nothing
    # and another candidate's deformation gradients copied over a library F file
    f_victim = files[3].with_name(files[3].name.replace(".parquet", ".F.parquet"))
    shutil.copy(files[2].with_name(files[2].name.replace(".parquet", ".F.parquet")), f_victim)
    verdict = audit_rollout_metadata(_expect(work))
    assert not verdict["passed"]
    assert any(str(victim) in p and "metadata.knockgs.theta" in p for p in verdict["problems"]), verdict["problems"]
    assert any(str(f_victim) in p and "metadata.knockgs.theta" in p for p in verdict["problems"]), verdict["problems"]
    assert len(verdict["problems"]) == 2, verdict["problems"]


@pytest.mark.slow
def test_a_rollout_of_another_probe_in_the_cache_is_caught(reference, tmp_path):
    from knockgs_core.assets import load_particles
    from knockgs_core.contract import load_contract
    from knockgs_core.rollout import run_rollout, write_rollout

    work = _cache_copy(reference, tmp_path)
    victim = sorted((work / P / "rollouts/pillow/lib/chunk0").glob("*[0-9].parquet"))[0]
    contract = load_contract("pillow", "ci")
    theta = json.loads(pq.read_schema(victim).metadata[b"knockgs"])["theta"]
    ro = run_rollout(contract, theta, "standard_y", particles=load_particles(work / P / "assets/pillow.particles.npz"))
    write_rollout(victim, ro)
    verdict = audit_rollout_metadata(_expect(work))
    assert any(str(victim) in p and "metadata.knockgs.probe" in p for p in verdict["problems"]), verdict["problems"]


@pytest.mark.slow
def test_a_truncated_rollout_with_its_old_time_stamp_is_caught_not_a_crash(reference, tmp_path):
    work = _cache_copy(reference, tmp_path)
    victim = sorted((work / P / "rollouts/pillow/lib/chunk1").glob("*[0-9].parquet"))[0]
    stat = victim.stat()
    data = victim.read_bytes()
    victim.write_bytes(data[: len(data) // 2])
    os.utime(victim, ns=(stat.st_atime_ns, stat.st_mtime_ns))
    for verdict in (audit_rollout_metadata(_expect(work)), audit_missing_frames([work / P / "rollouts/pillow"]),
                    audit_nonfinite([work / P / "rollouts/pillow"], [])):
        assert not verdict["passed"]
        assert [p for p in verdict["problems"] if str(victim) in p], verdict["problems"]


@pytest.mark.slow
def test_the_nonfinite_audit_scans_the_descriptor_tables(reference, tmp_path):
    table = tmp_path / "library.csv"
    df = pd.read_csv(reference / TABLE)
    df.loc[3, df.columns[-1]] = np.nan
    df.to_csv(table, index=False)
    clean = audit_nonfinite([], [reference / TABLE])
    assert clean["passed"], clean
    bad = audit_nonfinite([], [table])
    assert not bad["passed"] and str(table) in bad["problems"][0]
    # the workflow's non-finite audit reads the descriptor tables, and the rollout audit is part of `all`
    dry = snakemake(reference, "-n", *ARGS, f"{P}/audits/nonfinite.json")
    assert dry.returncode == 0, dry.stderr[-2000:]
    block = (dry.stdout + dry.stderr).split("rule audit_nonfinite:")[1].split("output:")[0]
    assert f"{P}/descriptors/pillow/library.csv" in block and f"{P}/descriptors/pillow/queries_main.csv" in block
    dry_all = snakemake(reference, "-n", *ARGS, "all")
    assert "audit_rollout_metadata" in dry_all.stdout + dry_all.stderr


@pytest.mark.slow
def test_an_unreadable_table_is_a_finding_not_a_crash(tmp_path):
    bad = tmp_path / "t.csv"
    bad.write_bytes(b"\xff\xfe\x00\x81" * 10)
    verdict = audit_nonfinite([], [bad])
    assert not verdict["passed"] and str(bad) in verdict["problems"][0]

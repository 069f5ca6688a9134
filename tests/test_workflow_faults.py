"""Workflow faults on the ci profile (issue 17): an interrupted run (Ctrl-C, SIGTERM or SIGKILL of
the whole process group) resumes to byte-identical tables, and the audits catch a cached
rollout that was swapped for another or truncated behind Snakemake's back, with a verdict
naming the file (not a crash); a file removed from a finished job's folder stops the job that
reads it with one line naming the file and the command that remakes the folder (issue 59). One
object (Pillow), the descriptor table of a candidate library of 12 (the first rows of
config/candidates.csv): the asset job and two library jobs of six, enough to stop one job while
the other writes, at a fifth of the full library's cost.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pandas as pd
import pyarrow.parquet as pq
import pytest

from _workflow import (LIBRARY_RUN_CONFIG, LIBRARY_TABLE, N_LIBRARY, copy_run, library_run, scratch_copy, small_library,
                       snakemake, snakemake_env)

from knockgs_core.audits import audit_missing_frames, audit_nonfinite, audit_rollout_metadata, rollout_expectations
from knockgs_core.errors import InputError
from knockgs_core.io import check_folder_outputs, check_job_inputs

P = "results/ci"
TABLE = LIBRARY_TABLE
ARGS = ("--cores", "2", *LIBRARY_RUN_CONFIG, "--")  # the shared small library's settings (tests/_workflow.py)
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


# --------------------------------------------------------------------------- a file removed from a finished job's folder

CHUNK1 = f"{P}/rollouts/pillow/lib/chunk1"
REMAKE = re.compile(r": snakemake (--cores 1 --force \S+(?: \S+)*)$")  # the command at the end of the refusal


def _removed(reference: Path, dest: Path, *paths: str) -> tuple[Path, dict]:
    """A copy of the reference run's cache (hard links) in a scratch copy of this workflow, with
    ``paths`` removed behind Snakemake's back; and the state (inode, size, time stamp) of every
    file left under its results."""
    work = small_library(copy_run(reference, dest, "assets", "rollouts", "descriptors"), N_CANDIDATES)
    for path in paths:
        (work / path).unlink()
    return work, _state(work)


def _state(work: Path) -> dict:
    """(inode, size, time stamp) of every file under the results of ``work``."""
    stats = {str(f.relative_to(work)): f.lstat() for f in sorted((work / P).rglob("*")) if not f.is_dir()}
    return {name: (st.st_ino, st.st_size, st.st_mtime_ns) for name, st in stats.items()}


def _refusal(out: subprocess.CompletedProcess, log: Path) -> str:
    """The one refusal line of a failed run, on its console (no traceback) and in the job's log."""
    console = out.stdout + out.stderr
    assert out.returncode != 0, console[-3000:]
    assert "Traceback" not in console, console[-3000:]
    lines = [line for line in console.splitlines() if line.startswith("knockgs workflow: error: ")]
    assert len(lines) == 1, console[-3000:]
    assert lines[0] in log.read_text().splitlines()
    return lines[0]


@pytest.mark.slow
def test_a_rollout_removed_from_a_finished_library_folder_is_named_with_the_command_that_remakes_it(reference, tmp_path):
    victim = f"{CHUNK1}/sE0.550000_sR1.200000.parquet"
    work, before = _removed(reference, tmp_path, victim, TABLE)
    out = snakemake(work, *ARGS, TABLE)
    line = _refusal(out, work / "logs/ci/descriptors/pillow/library.log")
    assert line.startswith(f"knockgs workflow: error: {victim}: field 'rollouts': missing from its folder"), line
    assert f"1 of the {N_CANDIDATES} files" in line, line
    assert not (work / TABLE).exists()
    assert _state(work) == before  # nothing written, no cached file replaced
    # the command named plans the folder's job again, and with it the table (chunk0 stays as it is)
    remake = REMAKE.search(line).group(1).split()
    assert remake[-1] == CHUNK1, line
    dry = snakemake(work, "-n", *remake, TABLE, *LIBRARY_RUN_CONFIG)
    assert dry.returncode == 0, dry.stderr[-2000:]
    assert set(re.findall(r"^\s+output: (.+)$", dry.stdout + dry.stderr, re.M)) == {CHUNK1, TABLE}, dry.stdout[-3000:]


@pytest.mark.slow
def test_a_deformation_gradient_file_removed_from_a_library_folder_stops_the_job_that_renders_it(reference, tmp_path):
    victim = f"{CHUNK1}/sE0.650000_sR1.000000.F.parquet"
    observations = f"{P}/ladder/observations/pillow/lib/chunk1.csv"  # rendered, tracked, observed: reads F
    work, before = _removed(reference, tmp_path, victim)
    out = snakemake(work, *ARGS, observations)
    line = _refusal(out, work / "logs/ci/ladder/observations/pillow/lib/chunk1.log")
    assert line.startswith(f"knockgs workflow: error: {victim}: field 'runs': missing from its folder"), line
    assert f"1 of the {N_CANDIDATES} files" in line and REMAKE.search(line).group(1).endswith(f"--force {CHUNK1}"), line
    assert not (work / observations).exists()
    assert _state(work) == before


def test_the_check_names_the_first_file_missing_from_an_existing_folder_and_counts_them(tmp_path, capfd):
    done = tmp_path / "chunk0"
    done.mkdir()
    files = [done / f"{i}.parquet" for i in range(3)]
    for f in files:
        f.write_bytes(b"x")
    check_folder_outputs(files)
    check_folder_outputs([tmp_path / "chunk1" / "0.parquet"])  # its folder is missing too: Snakemake makes it
    files[2].unlink()
    files[1].unlink()
    with pytest.raises(InputError) as refused:
        check_folder_outputs({"F": [None], "rollouts": files})
    assert (refused.value.source, refused.value.field) == (str(files[1]), "rollouts")
    assert "2 of the 3 files read from such folders are missing" in refused.value.message
    assert refused.value.message.endswith(f"snakemake --cores 1 --force {done}")
    # a workflow job checks the files its parameters name in its input folders, and only those
    # (the asset file is an input file, the camera no path): one line in its log and on the console, exit 2
    asset = tmp_path / "asset.ply"
    asset.write_bytes(b"ply")
    job = SimpleNamespace(input=[str(done), str(asset)],
                          params={"camera": {"fov": 30.0}, "runs": [{"rollout": str(f), "F": None} for f in files],
                                  "elsewhere": [str(tmp_path / "other" / "0.parquet")]})
    log = tmp_path / "job.log"
    with open(log, "w") as fh, pytest.raises(SystemExit) as stop:
        check_job_inputs(job, log=fh)
    assert stop.value.code == 2
    line = f"knockgs workflow: error: {InputError(files[1], 'runs', refused.value.message)}"
    assert capfd.readouterr().err.splitlines() == [line]
    assert log.read_text().splitlines() == [line]
    files[1].write_bytes(b"x")
    files[2].write_bytes(b"x")
    check_job_inputs(job)  # whole again: nothing to say
    assert capfd.readouterr().err == ""

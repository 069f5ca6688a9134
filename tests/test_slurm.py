"""The workflow on a real Slurm cluster (issue 22): the ci-profile Pillow library, made by
Snakemake's Slurm executor on a single-node cluster (``scripts/slurm-single-node.sh``), equals
the local run's, and a library job killed with ``scancel`` while it runs is submitted again
(``profiles/slurm``: ``retries``) with nothing lost.

The Slurm run makes a library of 12 candidates (the first rows of ``config/candidates.csv``:
the asset job, two library jobs of six and the descriptor job, every kind of job the executor
treats differently); its rollouts and descriptor table are compared with those of the same
library made by the local executor (the run the fault tests share).

It needs root, Debian's munge and Slurm packages and the executor plugin: ``.ci/run``
installs them (``scripts/slurm-single-node.sh install``); where any is missing the test is
skipped and says which.
"""

from __future__ import annotations

import importlib.util
import json
import os
import re
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pyarrow.parquet as pq
import pytest
import yaml

from _workflow import LIBRARY_RUN_CONFIG, LIBRARY_TABLE, N_LIBRARY, ROOT, library_run, scratch_copy, small_library, snakemake

SCRIPT = ROOT / "scripts" / "slurm-single-node.sh"
P = "results/ci"
TABLE = LIBRARY_TABLE
ARGS = (*LIBRARY_RUN_CONFIG, "--")  # the shared small library's settings (tests/_workflow.py)
N_CANDIDATES = N_LIBRARY


def _cluster_or_skip() -> bool:
    """Start the single-node cluster (True when this call started it)."""
    if importlib.util.find_spec("snakemake_executor_plugin_slurm") is None:
        pytest.skip("the Slurm executor plugin is not installed: pip install -e '.[slurm]'")
    if os.geteuid() != 0:
        pytest.skip("starting a Slurm cluster needs root (scripts/slurm-single-node.sh start)")
    if shutil.which("slurmctld") is None and not Path("/usr/sbin/slurmctld").exists():
        pytest.skip("Slurm is not installed: scripts/slurm-single-node.sh install (as root)")
    was_up = subprocess.run(["scontrol", "ping"], capture_output=True).returncode == 0
    out = subprocess.run(["bash", str(SCRIPT), "start"], capture_output=True, text=True, timeout=180)
    if out.returncode != 0:
        pytest.skip(f"the single-node Slurm cluster did not start: {out.stderr.strip()}")
    return not was_up


@pytest.fixture(scope="module")
def cluster():
    started = _cluster_or_skip()
    yield
    if started:  # a cluster that was already up is left as it was found
        subprocess.run(["bash", str(SCRIPT), "stop"], capture_output=True, timeout=120)


def _our_jobs(work: Path) -> list[tuple[str, str, str]]:
    """(job id, state, comment) of the Slurm jobs started from ``work``."""
    out = subprocess.run(["squeue", "-h", "-o", "%i|%T|%k|%Z"], capture_output=True, text=True)
    rows = [line.split("|") for line in out.stdout.splitlines() if line.count("|") == 3]
    return [(i, s, k) for i, s, k, z in rows if Path(z).resolve() == work.resolve()]


@pytest.mark.slow
def test_the_ci_library_through_slurm_equals_the_local_run_and_survives_a_scancel(cluster, tmp_path_factory):
    work = small_library(scratch_copy(tmp_path_factory.mktemp("slurm")), N_CANDIDATES)
    shutil.copytree(ROOT / "profiles", work / "profiles")
    # the profile as a user runs it; status checks every few seconds instead of every 20
    # (the single node runs two short jobs at a time)
    proc = subprocess.Popen([sys.executable, "-m", "snakemake", "--workflow-profile", "profiles/slurm",
                             "--slurm-init-seconds-before-status-checks", "2", *ARGS, TABLE],
                            cwd=work, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    killed = None
    deadline = time.monotonic() + 300
    try:
        while killed is None and time.monotonic() < deadline and proc.poll() is None:
            for job, state, comment in _our_jobs(work):
                if state == "RUNNING" and comment.startswith("rule_rollout_library"):
                    time.sleep(1.0)  # let it get into its rollouts
                    subprocess.run(["scancel", job], check=True)
                    killed = (job, comment)
                    break
            time.sleep(0.2)
        log, _ = proc.communicate(timeout=1200)
    finally:
        if proc.poll() is None:
            proc.kill()
            for job, _, _ in _our_jobs(work):
                subprocess.run(["scancel", job])
    assert killed is not None, "no library job was seen running under Slurm"
    assert proc.returncode == 0, log[-4000:]

    # every job went through Slurm
    slurm_logs = {p.parent.parent.name for p in (work / ".snakemake" / "slurm_logs").rglob("*.log")}
    assert slurm_logs == {"rule_asset", "rule_rollout_library", "rule_library_descriptors"}, slurm_logs
    # the cancelled job failed and was submitted again
    job, comment = killed
    assert f"SLURM jobid {job}" in log
    assert "CANCELLED" in log or "cancelled" in log.lower(), log[-4000:]
    wildcards = comment.removeprefix("rule_rollout_library_wildcards_")
    attempts = list((work / ".snakemake" / "slurm_logs" / "rule_rollout_library" / wildcards).glob("*.log"))
    assert len(attempts) >= 2, attempts

    # nothing lost: the local run's rollouts (values and metadata but the wall time) and
    # descriptor table (byte for byte), no temporary file left
    local = library_run(tmp_path_factory)  # the shared local run of the same library, read only
    lib = sorted(p.relative_to(work / P) for p in (work / P / "rollouts/pillow/lib").rglob("*.parquet"))
    assert len(lib) == 2 * N_CANDIDATES  # positions and deformation gradients
    for rel in lib:
        ours, theirs = pq.read_table(work / P / rel), pq.read_table(local / P / rel)
        assert ours.equals(theirs), rel
        meta = [{k: v for k, v in json.loads(t.schema.metadata.get(b"knockgs", b"{}")).items() if k != "wall_seconds"}
                for t in (ours, theirs)]
        assert meta[0] == meta[1], rel
    assert (work / TABLE).read_bytes() == (local / TABLE).read_bytes()
    assert [p for p in (work / P).rglob("*") if ".tmp" in p.name] == []


def test_the_script_refuses_clearly_without_root_or_a_command(tmp_path):
    # an unknown command: usage, exit 2
    out = subprocess.run(["bash", str(SCRIPT), "restart"], capture_output=True, text=True)
    assert out.returncode == 2 and "usage:" in out.stderr
    if os.geteuid() == 0:
        # as root, a slurm.conf that the script did not write is never overwritten
        fake = tmp_path / "etc"
        env = {**os.environ, "SLURM_CONF": str(fake / "slurm.conf")}
        fake.mkdir()
        (fake / "slurm.conf").write_text("ClusterName=theirs\n")
        out = subprocess.run(["bash", str(SCRIPT), "config"], capture_output=True, text=True, env=env)
        assert out.returncode == 2, out
        assert "not written by this script" in out.stderr
        assert (fake / "slurm.conf").read_text() == "ClusterName=theirs\n"
    else:
        out = subprocess.run(["bash", str(SCRIPT), "start"], capture_output=True, text=True)
        assert out.returncode == 2 and "needs root" in out.stderr


def _gpu_rules() -> set[str]:
    """The rules whose resources request a GPU on a CUDA profile (``gpu=1 if ON_GPU``)."""
    rules = set()
    for smk in (ROOT / "workflow" / "rules").glob("*.smk"):
        for block in re.split(r"^(?=(?:rule|checkpoint) )", smk.read_text(), flags=re.M):
            head = re.match(r"(?:rule|checkpoint) (\w+):", block)
            if head and "gpu=1 if ON_GPU" in block:
                rules.add(head.group(1))
    return rules


def _device_rules() -> set[str]:
    """The rules that hand the profile's device to their script (``device=DEVICE``): they
    simulate or render on it."""
    rules = set()
    for smk in (ROOT / "workflow" / "rules").glob("*.smk"):
        for block in re.split(r"^(?=(?:rule|checkpoint) )", smk.read_text(), flags=re.M):
            head = re.match(r"(?:rule|checkpoint) (\w+):", block)
            if head and re.search(r"^\s+device=DEVICE,$", block, flags=re.M):
                rules.add(head.group(1))
    return rules


def test_every_rule_that_runs_on_the_device_requests_a_gpu_and_goes_to_the_gpu_partition():
    # a rule that simulates or renders on the profile's device must hold a GPU of the run's
    # budget (--resources gpu=N; else it waits on a card other jobs hold, or starts beside N
    # GPU jobs) and go to the GPU partition on a cluster (else it meets no GPU there)
    device_rules = _device_rules()
    assert {"rollout_library", "render", "discrepancy_run", "passive_protocol", "ladder_observe_targets"} <= device_rules
    assert device_rules == _gpu_rules()
    profile = yaml.safe_load((ROOT / "profiles/slurm-gpu/config.yaml").read_text())
    assert set(profile["set-resources"]) == device_rules


def _dry_run_jobs(stdout: str) -> dict[str, list[str]]:
    """rule -> the ``resources:`` lines of its planned jobs in a dry run's output."""
    jobs: dict[str, list[str]] = {}
    for block in re.split(r"^(?=(?:rule|checkpoint) \w+:$)", stdout, flags=re.M):
        head = re.match(r"(?:rule|checkpoint) (\w+):", block)
        res = re.search(r"^\s+resources: (.*)$", block, flags=re.M)
        if head and res:
            jobs.setdefault(head.group(1), []).append(res.group(1))
    return jobs


def test_the_gpu_profile_sends_exactly_the_gpu_rules_to_the_gpu_partition(tmp_path):
    if importlib.util.find_spec("snakemake_executor_plugin_slurm") is None:
        pytest.skip("the Slurm executor plugin is not installed: pip install -e '.[slurm]'")
    profile = yaml.safe_load((ROOT / "profiles/slurm-gpu/config.yaml").read_text())
    assert set(profile["set-resources"]) == _gpu_rules()
    for name in ("slurm", "slurm-gpu"):
        cfg = yaml.safe_load((ROOT / f"profiles/{name}/config.yaml").read_text())
        assert cfg["executor"] == "slurm" and cfg["retries"] >= 1 and cfg["slurm-status-command"] == "squeue"
    # the paper profile planned through the GPU profile (no cluster needed for a dry run)
    work = scratch_copy(tmp_path / "w")
    shutil.copytree(ROOT / "profiles", work / "profiles")
    out = snakemake(work, "-n", "--workflow-profile", "profiles/slurm-gpu", "--configfile=config/paper.yaml", "all")
    assert out.returncode == 0, out.stderr[-3000:]
    jobs = _dry_run_jobs(out.stdout + out.stderr)
    assert {"rollout_library", "rollout_eval"} <= set(jobs)
    for rule, lines in jobs.items():
        for line in lines:
            on_gpu = "gpu=1" in line.split(", ") and "slurm_partition=gpu" in line.split(", ")
            assert on_gpu == (rule in _gpu_rules()), (rule, line)

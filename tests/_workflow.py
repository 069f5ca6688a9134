"""Helpers of the workflow tests: a scratch copy of the workflow, a Snakemake call in it, and the
one ci-profile run that every test reading its outputs shares."""

from __future__ import annotations

import contextlib
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parents[1]
CI = "results/ci"  # every output of a ci-profile run lies under it

#: The shared run's settings (``config/ci_tests.yaml``, which :func:`scratch_copy` writes): the ci
#: profile on the Pillow alone, with the main target split only (the ci profile has three
#: alternative splits: each adds a descriptor table, six estimates, about 25 evaluation jobs and no
#: code path; the splits table's rows over several splits are tested on their own,
#: ``tests/test_diagnostics.py``, and the alternative splits' jobs in the ci profile's plan,
#: ``tests/test_workflow.py``) and one flow-noise rung of the observation ladder (the ci profile
#: has three: each adds a descriptor table, five estimates and their Probe-B rollouts, and no code
#: path).
CI_TESTS_OVERRIDES = {"diagnostics": {"splits": []}, "ladder": {"depth_noise": [0.01]}}
#: The shared run's estimators: the ci profile's six but the k-nearest and the global ridge, each
#: of which adds five estimates, their evaluation rollouts and renders (about 20 jobs) and no code
#: path (every method goes through the same estimate, evaluation and render rules; the two are
#: tested on the authors' Ficus data in tests/test_calibration.py and through the command in
#: tests/test_cli_calibrate.py).
CI_TESTS_METHODS = ["fixed_default", "response_nearest", "local_ridge", "parameter_nearest_oracle"]
#: The small library's runs (:func:`library_run`, the fault and Slurm tests): six candidates a job.
LIBRARY_RUN_CONFIG = ("--configfile=config/ci_tests.yaml", "--config", "objects=[pillow]")
#: The shared run's: the same, the library in two jobs of 27 candidates (the ci profile's six a
#: job keep more cores busy; on the two cores of a test run each of the other seven jobs, and the
#: ladder's and the passive route's job of each chunk, pays a process and Warp start-up of about
#: 2.5 s and nothing else).
CI_RUN_CONFIG = (*LIBRARY_RUN_CONFIG, "library_chunk=27")

#: What the shared run makes: the Pillow's main, render, diagnostics, probe-shift, passive,
#: ladder and convergence tables and figures, and the audits that read them.
CI_RUN_TARGETS = tuple(f"{CI}/{path}" for path in (
    "tables/main_pillow.csv", "tables/render_pillow.csv", "figures/qualitative_pillow.png", "figures/compare_pillow.gif",
    "figures/main_pillow.png", "audits/leakage.json", "audits/duplicates.json", "audits/nonfinite.json",
    "audits/missing_frames.json", "tables/splits_pillow.csv", "tables/sensitivity_size_pillow.csv",
    "tables/identifiability_pillow.csv", "tables/duration_pillow.csv", "tables/contact_pillow.csv",
    "tables/passive_active_pillow.csv", "audits/rollout_metadata.json", "tables/ladder_pillow.csv",
    "tables/convergence_pillow.csv"))


def scratch_copy(dest: Path) -> Path:
    """Copy the Snakefile, ``workflow/`` and ``config/`` into ``dest`` (results stay there), and
    write the shared run's profile ``config/ci_tests.yaml`` there (:data:`CI_TESTS_OVERRIDES`,
    :data:`CI_TESTS_METHODS`)."""
    dest.mkdir(parents=True, exist_ok=True)
    shutil.copy(ROOT / "Snakefile", dest)
    shutil.copytree(ROOT / "workflow", dest / "workflow")
    shutil.copytree(ROOT / "config", dest / "config")
    ci = yaml.safe_load((dest / "config" / "ci.yaml").read_text())
    for key, value in CI_TESTS_OVERRIDES.items():
        ci[key].update(value)
    ci["methods"] = list(CI_TESTS_METHODS)
    ci["method_params"] = {m: p for m, p in ci["method_params"].items() if m in CI_TESTS_METHODS}
    (dest / "config" / "ci_tests.yaml").write_text(yaml.safe_dump(ci, sort_keys=False))
    return dest


def small_library(work: Path, n: int) -> Path:
    """Cut the candidate library of the scratch copy ``work`` to the first ``n`` rows of
    ``config/candidates.csv``: its library jobs are the first ``n / library_chunk`` jobs of the
    full library, with the same rollouts (and the first ``n`` rows of its descriptor table)."""
    table = work / "config" / "candidates.csv"
    lines = table.read_text().splitlines(keepends=True)
    head = sum(1 for line in lines if line.startswith("#")) + 1  # comments and the header
    table.write_text("".join(lines[: head + n]))
    return work


def snakemake_env() -> dict:
    """The environment of the tests' Snakemake runs that do not use Slurm.

    Snakemake loads its Slurm executor plugin (the ``slurm`` extra) at every start, and the
    plugin asks ``scontrol show config`` for the controller's MinJobAge when it is imported.
    Where Slurm is installed but no controller runs (``.ci/run`` installs it; the Slurm test
    starts the cluster only for itself), that call waits about 9 s for the controller, at each
    of the test run's many Snakemake starts. These runs see an ``scontrol`` first on ``PATH``
    that fails at once, so the plugin takes its default, as on a machine without Slurm."""
    shim = Path(tempfile.gettempdir()) / f"knockgs-tests-{os.getuid()}" / "no-slurm"
    if not (shim / "scontrol").exists():
        shim.mkdir(parents=True, exist_ok=True)
        tmp = shim / f".scontrol.{os.getpid()}"
        tmp.write_text("#!/bin/sh\necho 'scontrol: no Slurm controller in this test run' >&2\nexit 1\n")
        tmp.chmod(0o755)
        os.replace(tmp, shim / "scontrol")
    return {**os.environ, "PATH": f"{shim}{os.pathsep}{os.environ.get('PATH', '')}"}


def snakemake(work: Path, *args: str) -> subprocess.CompletedProcess:
    """``snakemake ARGS`` in ``work`` (the installed Snakemake), output captured, without Slurm
    (:func:`snakemake_env`)."""
    return subprocess.run([sys.executable, "-m", "snakemake", *args], cwd=work, capture_output=True, text=True,
                          env=snakemake_env())


@contextlib.contextmanager
def _exclusive(lock: Path):
    """Hold ``lock`` (a file) exclusively: one process of the test run at a time."""
    import fcntl

    with open(lock, "w") as fh:
        fcntl.flock(fh, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(fh, fcntl.LOCK_UN)


def shared_root(tmp_path_factory) -> Path:
    """The temporary folder shared by every process of this test run (pytest-xdist's workers
    each have a folder of their own below it)."""
    base = tmp_path_factory.getbasetemp()
    return base.parent if os.environ.get("PYTEST_XDIST_WORKER") else base


def shared_run(tmp_path_factory, name: str, *args: str, prepare=None) -> Path:
    """``snakemake ARGS`` in a scratch copy made once per test run, whichever process asks first
    (the others wait for it under a file lock, then read it); ``prepare(work)`` edits the copy
    before the run. Tests only read what it holds: a test that changes files works on a copy
    (:func:`copy_run`)."""
    root = shared_root(tmp_path_factory)
    work, done, failed = root / f"shared-{name}", root / f"shared-{name}.done", root / f"shared-{name}.failed"
    with _exclusive(root / f"shared-{name}.lock"):
        if failed.exists():
            raise AssertionError(f"the shared run {name} failed in another process:\n{failed.read_text()}")
        if not done.exists():
            shutil.rmtree(work, ignore_errors=True)
            scratch_copy(work)
            if prepare is not None:
                prepare(work)
            out = snakemake(work, *args)
            if out.returncode != 0:
                failed.write_text(out.stderr[-4000:])
                raise AssertionError(out.stderr[-4000:])
            done.touch()
    return work


def ci_run(tmp_path_factory) -> Path:
    """The shared ci-profile run of the Pillow (:data:`CI_RUN_TARGETS` under :data:`CI_RUN_CONFIG`)."""
    return shared_run(tmp_path_factory, "ci", *CI_RUN_TARGETS, "--cores", "2", *CI_RUN_CONFIG)


#: the candidates of the shared small library (:func:`library_run`)
N_LIBRARY = 12
LIBRARY_TABLE = f"{CI}/descriptors/pillow/library.csv"


def library_run(tmp_path_factory) -> Path:
    """The shared run of a small library: the Pillow's descriptor table of the first
    :data:`N_LIBRARY` candidates (:func:`small_library`) under :data:`LIBRARY_RUN_CONFIG`, the
    asset job, two library jobs of six and the descriptor job (the fault and Slurm tests' reference)."""
    return shared_run(tmp_path_factory, "library", LIBRARY_TABLE, "--cores", "2", *LIBRARY_RUN_CONFIG,
                      prepare=lambda work: small_library(work, N_LIBRARY))


def copy_run(run: Path, dest: Path, *parts: str) -> Path:
    """A scratch copy of the workflow in ``dest`` holding ``parts`` of the run's results (paths
    below ``results/ci``) as hard links, so a Snakemake started in it finds them up to date and
    makes only what is missing. Snakemake replaces a file it remakes rather than writing into
    it, so the run's own files stay as they are; a test that edits files in place copies them."""
    scratch_copy(dest)
    for part in parts:
        src, out = run / CI / part, dest / CI / part
        if src.is_dir():
            shutil.copytree(src, out, copy_function=os.link)
        else:
            out.parent.mkdir(parents=True, exist_ok=True)
            os.link(src, out)
    return dest

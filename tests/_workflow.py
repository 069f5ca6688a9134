"""Helpers of the workflow tests: a scratch copy of the workflow and a Snakemake call in it."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def scratch_copy(dest: Path) -> Path:
    """Copy the Snakefile, ``workflow/`` and ``config/`` into ``dest`` (results stay there)."""
    dest.mkdir(parents=True, exist_ok=True)
    shutil.copy(ROOT / "Snakefile", dest)
    shutil.copytree(ROOT / "workflow", dest / "workflow")
    shutil.copytree(ROOT / "config", dest / "config")
    return dest


def snakemake(work: Path, *args: str) -> subprocess.CompletedProcess:
    """``snakemake ARGS`` in ``work`` (the installed Snakemake), output captured."""
    return subprocess.run([sys.executable, "-m", "snakemake", *args], cwd=work, capture_output=True, text=True)

"""Every command of the README's "## Commands" section runs as written, in order.

The commands are taken from the section's ``bash`` block (continuation lines joined,
trailing comments dropped) and run in a temporary directory that holds the project's
``config/`` and ``tests/data/`` (linked), so that names and relative paths resolve as they
do from the repository root, and nothing is written into the checkout. ``knockgs`` is run
as ``python -m knockgs_core`` with this interpreter.
"""

from __future__ import annotations

import os
import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def readme_commands(text: str) -> list[list[str]]:
    """The commands of the first ``bash`` block under ``## Commands``, as argument lists."""
    section = re.search(r"^## Commands\n(.*?)(?=^## )", text, flags=re.S | re.M)
    assert section, "README.md has no '## Commands' section"
    block = re.search(r"```bash\n(.*?)```", section.group(1), flags=re.S)
    assert block, "the Commands section has no bash block"
    joined = re.sub(r"\\\n\s*", " ", block.group(1))
    commands = []
    for line in joined.splitlines():
        args = shlex.split(line, comments=True)
        if args:
            commands.append(args)
    return commands


def test_readme_commands_parse():
    cmds = readme_commands((ROOT / "README.md").read_text())
    assert cmds and all(c[0] == "knockgs" for c in cmds)
    assert any(c[1:3] == ["render", "frames"] for c in cmds)
    assert readme_commands("## Commands\n\n```bash\nknockgs a \\\n    --b c  # note\n```\n\n## Next\n") == [
        ["knockgs", "a", "--b", "c"]]


@pytest.mark.slow
def test_readme_commands_run_in_order(tmp_path):
    cmds = readme_commands((ROOT / "README.md").read_text())
    (tmp_path / "config").symlink_to(ROOT / "config", target_is_directory=True)
    (tmp_path / "tests").mkdir()
    (tmp_path / "tests" / "data").symlink_to(ROOT / "tests" / "data", target_is_directory=True)
    env = {k: v for k, v in os.environ.items() if k not in ("KNOCKGS_CONFIG_DIR", "KNOCKGS_DEVICE")}
    for args in cmds:
        proc = subprocess.run([sys.executable, "-m", "knockgs_core", *args[1:]], cwd=tmp_path, env=env,
                              capture_output=True, text=True, timeout=300)
        assert proc.returncode == 0, f"{shlex.join(args)}\n{proc.stderr[-2000:]}"
        assert "Warp CUDA warning" not in proc.stderr  # a CPU run prints no Warp start-up message
    demo = tmp_path / "demo"
    for name in ("pillow.ply", "pillow.scene.npz", "pillow.particles.npz", "r.parquet", "r.F.parquet", "est.json",
                 "r.rgbd.npz", "tracks.parquet", "tracks_queries.csv"):
        assert (demo / name).stat().st_size > 0, name
    assert sorted(p.name for p in (demo / "frames").iterdir()) == ["frame_0000.png", "frame_0015.png", "frame_0030.png"]
    assert len(list((demo / "ply").glob("frame_*.ply"))) == 31
    assert not [p for p in demo.rglob(".*.tmp*")]  # no temporary file of the atomic writers left behind

"""The library as a user installs it: a non-editable ``pip install .`` into a fresh virtual
environment, used from a directory that is not the project.

The environment is made ``--without-pip``; a ``.pth`` file in it adds the running
interpreter's site-packages folders as site folders (``--system-site-packages`` would see the
*base* interpreter's, not those of a virtual environment the tests run in), and the package
is installed with ``--no-deps --no-build-isolation --no-index``, so nothing is downloaded:
the dependencies (and pip, setuptools) come from the test environment. The project's own
editable install stays visible through those folders, after the new environment's own, so
every check first asserts that the installed copy, not the source tree, is the one imported.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _can_build_wheels() -> bool:
    """setuptools with a built-in ``bdist_wheel`` (>= 70.1), or the ``wheel`` package."""
    try:
        import setuptools
    except ImportError:
        return False
    try:
        major, minor = (int(x) for x in setuptools.__version__.split(".")[:2])
    except ValueError:
        return False
    if (major, minor) >= (70, 1):
        return True
    try:
        import wheel  # noqa: F401
    except ImportError:
        return False
    return True


@pytest.fixture(scope="module")
def installed(tmp_path_factory):
    """(python, knockgs, env, run_dir): a fresh venv holding a non-editable install."""
    if not _can_build_wheels():
        pytest.skip("building the wheel needs setuptools >= 70.1 or wheel (the 'test' extra installs them)")
    base = tmp_path_factory.mktemp("install")
    src = base / "src-copy"  # build from a copy: the build leaves build/ and *.egg-info behind
    src.mkdir()
    for name in ("pyproject.toml", "README.md"):
        shutil.copy2(ROOT / name, src / name)
    shutil.copytree(ROOT / "src", src / "src", ignore=shutil.ignore_patterns("__pycache__", "*.egg-info"))
    venv = base / "venv"
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(venv)], check=True)
    bindir = venv / ("Scripts" if os.name == "nt" else "bin")
    python = bindir / "python"
    own = subprocess.run([str(python), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                         capture_output=True, text=True, check=True).stdout.strip()
    # the test environment's packages, behind the new environment's own (a venv or not)
    outer = [p for p in sys.path if p and Path(p).is_dir() and Path(p).name in ("site-packages", "dist-packages")]
    (Path(own) / "_test_environment.pth").write_text("".join(f"import site; site.addsitedir({p!r})\n" for p in outer))
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "KNOCKGS_CONFIG_DIR", "KNOCKGS_DEVICE")}
    env["PIP_DISABLE_PIP_VERSION_CHECK"] = "1"
    pip = [str(python), "-m", "pip", "install", "-q", "--no-deps", "--no-build-isolation", "--no-index", str(src)]
    proc = subprocess.run(pip, env=env, capture_output=True, text=True)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    run_dir = base / "elsewhere"
    run_dir.mkdir()
    return python, bindir / "knockgs", env, run_dir


def _run(args, installed, **kw):
    _, _, env, run_dir = installed
    return subprocess.run([str(a) for a in args], cwd=run_dir, env=env, capture_output=True, text=True, timeout=300, **kw)


@pytest.mark.slow
def test_the_installed_copy_is_imported_with_its_schema(installed):
    python, _, _, run_dir = installed
    code = ("import knockgs_core, knockgs_core.contract as c; "
            "print(knockgs_core.__file__); print(c.schema_path())")
    proc = _run([python, "-c", code], installed)
    assert proc.returncode == 0, proc.stderr
    module, schema = proc.stdout.split()
    venv = Path(python).parents[1].resolve()
    assert Path(module).resolve().is_relative_to(venv), module  # not the source tree
    assert Path(schema).resolve().is_relative_to(venv) and Path(schema).is_file()
    assert not Path(schema).resolve().is_relative_to(ROOT)


@pytest.mark.slow
def test_a_contract_given_by_path_is_validated_and_simulated(installed):
    _, knockgs, _, run_dir = installed
    contracts = run_dir / "contracts"
    contracts.mkdir(exist_ok=True)
    shutil.copy2(ROOT / "config" / "objects" / "pillow.yaml", contracts / "pillow.yaml")
    out = run_dir / "r.parquet"
    proc = _run([knockgs, "simulate", "--object", "contracts/pillow.yaml", "--profile", "ci", "--probe", "standard_x",
                 "--quiet", "-o", out], installed)
    assert proc.returncode == 0, proc.stderr
    assert "Warp CUDA warning" not in proc.stderr and "Warp " not in proc.stdout  # a CPU run prints no Warp banner
    import pyarrow.parquet as pq

    meta = pq.read_schema(out).metadata[b"knockgs"]
    assert b'"object": "pillow"' in meta and b'"profile": "ci"' in meta
    assert pq.read_metadata(out).num_rows > 0

    # validation runs against the packaged schema: a typo is named with its field
    bad = contracts / "typo.yaml"
    bad.write_text((contracts / "pillow.yaml").read_text().replace("name: pillow", "name: typo\nnmae: x"))
    proc = _run([knockgs, "asset", "summary", "contracts/typo.yaml", "--profile", "ci"], installed)
    assert proc.returncode == 2
    assert "typo.yaml" in proc.stderr and "nmae" in proc.stderr


@pytest.mark.slow
def test_a_name_outside_a_project_says_where_it_looked(installed):
    _, knockgs, _, _ = installed
    proc = _run([knockgs, "asset", "summary", "pillow", "--profile", "ci"], installed)
    assert proc.returncode == 2
    assert "config/objects" in proc.stderr and "path" in proc.stderr

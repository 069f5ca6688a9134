"""The reader side of safety (issue 59): every input checked before work, read within bounds,
judged for plausibility, and named in its error; one test per class of the issue.

Each refusal is checked the same way (:class:`Refusal`): exit code 2, one line on stderr
naming the file and the field, no traceback, no file of the case's folder or of the shared
inputs changed, created or left behind. The command runs in-process under a 20 s alarm, so a
read that blocks (a FIFO) fails the test at once instead of hanging it; the cases that need the
real entry point run it as a subprocess under a timeout. The shared inputs (a ci-profile Pillow
asset and one rollout with its deformation gradients) are built once per module, in ~6 s.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from knockgs_core.cli import main
from knockgs_core.descriptors import FEATURE_NAMES as FEATURES

ROOT = Path(__file__).resolve().parents[1]


def _ok(*args) -> None:
    assert main([str(a) for a in args]) == 0, args


@pytest.fixture(scope="module")
def shared(tmp_path_factory):
    """A ci-profile Pillow asset (normalized PLY, scene, particles) and its standard_x rollout
    with F."""
    S = tmp_path_factory.mktemp("shared")
    _ok("asset", "make", "pillow", "--profile", "ci", "--normalized", "-o", S / "pillow.ply",
        "--particles", S / "pillow.particles.npz")
    _ok("simulate", "--object", "pillow", "--profile", "ci", "--probe", "standard_x", "--particles",
        S / "pillow.particles.npz", "-o", S / "r.parquet", "--export-F", S / "r.F.parquet", "--quiet")
    return S


def _snapshot(*folders: Path) -> dict:
    out = {}
    for folder in folders:
        for p in sorted(Path(folder).rglob("*")):
            st = os.lstat(p)
            if p.is_symlink():
                out[str(p)] = ("link", os.readlink(p))
            elif p.is_file():
                out[str(p)] = (hashlib.sha256(p.read_bytes()).hexdigest(), st.st_mtime_ns)
            else:
                out[str(p)] = (st.st_mode, st.st_mtime_ns)
    return out


class _Hang(BaseException):
    """Raised by the alarm: a command that blocked (not an Exception, so no handler maps it)."""


class Refusal:
    def __init__(self, shared: Path, tmp: Path, capsys):
        self.shared, self.tmp, self.capsys = shared, tmp, capsys

    def __call__(self, *args, names=(), says=(), code: int = 2) -> str:
        before = _snapshot(self.shared, self.tmp)

        def hang(signum, frame):
            raise _Hang(f"blocked for 20 s: {args}")

        old = signal.signal(signal.SIGALRM, hang)
        signal.alarm(20)
        try:
            rc = main([str(a) for a in args])
        except SystemExit as exc:  # argparse usage errors
            rc = exc.code
        finally:
            signal.alarm(0)
            signal.signal(signal.SIGALRM, old)
        err = self.capsys.readouterr().err
        assert rc == code, err
        lines = [line for line in err.splitlines() if line.strip()]
        assert len(lines) == 1, err
        line = lines[0]
        assert line.startswith("knockgs ") and "Traceback" not in err and "error: " in line, line
        for text in (*map(str, names), *says):
            assert text in line, (text, line)
        assert _snapshot(self.shared, self.tmp) == before, "a file changed, appeared or was left behind"
        return line


@pytest.fixture
def refuse(shared, tmp_path, capsys):
    return Refusal(shared, tmp_path, capsys)


def _fifo(path: Path) -> Path:
    os.mkfifo(path)
    return path


def _library(path: Path, features: np.ndarray, n: int | None = None) -> Path:
    """A library CSV of candidates on the level grid, with the given features [n, 5]."""
    features = np.atleast_2d(features)
    n = len(features)
    se = np.linspace(0.5, 1.15, n)
    sr = np.linspace(0.75, 1.75, n)[::-1]
    rows = ["case_name,E_scale,density_scale," + ",".join(FEATURES)]
    rows += [f"c{i},{se[i]:.4f},{sr[i]:.4f}," + ",".join(f"{v:.10g}" for v in features[i]) for i in range(n)]
    path.write_text("\n".join(rows) + "\n")
    return path


def _queries(path: Path, rng) -> Path:
    rows = ["case_name," + ",".join(FEATURES)]
    rows += [f"q{i}," + ",".join(f"{v:.6g}" for v in rng.uniform(0.1, 1.0, 5)) for i in range(2)]
    path.write_text("\n".join(rows) + "\n")
    return path


@pytest.fixture
def rng():
    return np.random.default_rng(59)


# --------------------------------------------------------------------------- 1. not regular, unbounded


def test_an_input_that_is_not_a_regular_file_is_refused_before_it_is_read(shared, refuse, tmp_path, rng):
    lib = _library(tmp_path / "lib.csv", rng.uniform(0.1, 1.0, (12, 5)))
    q = _queries(tmp_path / "q.csv", rng)
    out = tmp_path / "est.json"
    cal = ("calibrate", "--method", "local_ridge", "--output", out)
    refuse(*cal, "--library", _fifo(tmp_path / "lib.fifo"), "--queries", q,
           names=("lib.fifo", "--library"), says=("FIFO",))
    refuse(*cal, "--library", lib, "--queries", "/dev/zero", names=("/dev/zero", "--queries"), says=("character device",))
    refuse(*cal, "--library", tmp_path, "--queries", q, names=(tmp_path, "--library"), says=("a folder",))
    S = shared
    ply = ("render", "ply", "--asset", S / "pillow.ply", "--rollout", S / "r.parquet", "-o", tmp_path / "plyout")
    refuse("render", "ply", "--asset", _fifo(tmp_path / "a.fifo"), "--rollout", S / "r.parquet", "-o", tmp_path / "o",
           names=("a.fifo", "--asset"), says=("FIFO",))
    refuse("render", "ply", "--asset", S / "pillow.ply", "--rollout", "/dev/zero", "-o", tmp_path / "o",
           names=("/dev/zero", "--rollout"), says=("character device",))
    refuse(*ply, "--scene", tmp_path, names=(tmp_path, "--scene"), says=("a folder",))
    refuse("simulate", "--object", _fifo(tmp_path / "c.fifo.yaml"), "--profile", "ci", "--probe", "standard_x",
           "-o", tmp_path / "x.parquet", names=("c.fifo.yaml", "--object"), says=("FIFO",))
    refuse("simulate", "--object", "pillow", "--profile", "ci", "--probe", "standard_x", "--particles",
           _fifo(tmp_path / "p.fifo.npz"), "-o", tmp_path / "x.parquet", names=("p.fifo.npz", "--particles"))
    refuse("observe", "tracks", _fifo(tmp_path / "r.fifo.npz"), "-o", tmp_path / "t.parquet",
           names=("r.fifo.npz", "frames"), says=("FIFO",))
    refuse("discrepancy", "table", _fifo(tmp_path / "row.fifo.json"), "--csv", tmp_path / "t.csv", "--md",
           tmp_path / "t.md", names=("row.fifo.json", "ROW.json"))
    refuse("discrepancy", "evaluate", "--run-dir", lib, "--truth-dir", tmp_path, "-o", tmp_path / "row.json",
           names=("lib.csv", "--run-dir"), says=("not a folder",))
    (tmp_path / "gone.csv").symlink_to(tmp_path / "nowhere.csv")
    refuse(*cal, "--library", tmp_path / "gone.csv", "--queries", q, names=("gone.csv",), says=("broken symbolic link",))
    big = tmp_path / "big.yaml"  # a sparse 5 MB contract: beyond the 4 MiB a YAML input may be
    with open(big, "wb") as fh:
        fh.truncate(5_000_000)
    refuse("simulate", "--object", big, "--profile", "ci", "--probe", "standard_x", "-o", tmp_path / "x.parquet",
           names=("big.yaml", "--object"), says=("5 MB", "more than"))


def test_a_fifo_input_does_not_block_the_real_command(tmp_path):
    """The entry point as a user runs it, under a timeout: refused in seconds, not a hang."""
    fifo = _fifo(tmp_path / "c.fifo.yaml")
    env = {**os.environ, "PYTHONPATH": str(ROOT / "src")}
    p = subprocess.run([sys.executable, "-m", "knockgs_core", "simulate", "--object", str(fifo), "--profile", "ci",
                        "--probe", "standard_x", "-o", str(tmp_path / "x.parquet")],
                       capture_output=True, text=True, timeout=60, env=env)
    assert p.returncode == 2, p.stderr
    assert p.stderr.count("\n") == 1 and "FIFO" in p.stderr and "c.fifo.yaml" in p.stderr, p.stderr
    assert sorted(os.listdir(tmp_path)) == ["c.fifo.yaml"]


# --------------------------------------------------------------------------- 2. outputs checked whole


def test_an_output_is_checked_whole_before_the_first_file_is_written(shared, refuse, tmp_path):
    S = shared
    ply = ("render", "ply", "--asset", S / "pillow.ply", "--rollout", S / "r.parquet", "--frames", "1,0")
    out = tmp_path / "plyout"
    out.mkdir()
    _fifo(out / "frame_0000.ply")  # frame 1 would be written first: refused before it is
    refuse(*ply, "-o", out, names=("frame_0000.ply", "--output"), says=("FIFO",))
    os.unlink(out / "frame_0000.ply")
    (out / "frame_0000.ply").symlink_to(S / "r.parquet")  # a link to an input
    refuse(*ply, "-o", out, names=("frame_0000.ply",))
    os.unlink(out / "frame_0000.ply")
    (out / "frame_0000.ply").symlink_to(tmp_path / "elsewhere.ply")  # a dangling link to a file elsewhere
    refuse(*ply, "-o", out, names=("frame_0000.ply",))
    os.unlink(out / "frame_0000.ply")
    (tmp_path / "elsewhere.ply").write_text("x")
    (out / "frame_0000.ply").symlink_to(tmp_path / "elsewhere.ply")  # a link to a file elsewhere
    refuse(*ply, "-o", out, names=("frame_0000.ply",), says=("symbolic link",))
    sim = ("simulate", "--object", "pillow", "--profile", "ci", "--probe", "standard_x", "--quiet")
    refuse(*sim, "-o", f"{tmp_path}/newdir/", names=("newdir/", "--output"), says=("folder",))
    refuse(*sim, "-o", tmp_path / ("n" * 256 + ".parquet"), names=("--output",), says=("file name",))


def test_a_long_valid_output_name_gets_a_temporary_name_that_fits(tmp_path):
    from knockgs_core.io import write_text

    target = tmp_path / ("n" * 242 + ".parquet")  # 250 bytes: fits; ".NAME.tmpPID.parquet" would not
    write_text(target, "rows\n")
    assert target.read_text() == "rows\n"
    assert os.listdir(tmp_path) == [target.name]


# --------------------------------------------------------------------------- 3. values that mean nothing


def _edit_long(src: Path, dest: Path, edit) -> Path:
    t = pq.read_table(src)
    cols = {n: t.column(n).to_numpy().copy() for n in t.column_names}
    edit(cols)
    pq.write_table(pa.table(cols).replace_schema_metadata(t.schema.metadata), dest)
    return dest


def test_a_rollout_that_parses_but_means_nothing_is_refused(shared, refuse, tmp_path):
    S = shared
    cases = {  # rollout edit, F edit, the field named
        "mirror": (None, lambda c: c.__setitem__("F00", np.full_like(c["F00"], -1.0)), "det F"),
        "huge": (None, lambda c: [c.__setitem__(k, np.full_like(c[k], 1e30)) for k in ("F00", "F11", "F22")], "F"),
        "far": (lambda c: c["x"].__setitem__(5, 1e30), None, "outside the simulation domain"),
        "ids": (lambda c: c.__setitem__("particle", c["particle"] + 1), None, "ids must be 0.."),
    }
    for name, (edit_x, edit_F, says) in cases.items():
        case = tmp_path / name
        case.mkdir()
        ro = case / "r.parquet"
        _edit_long(S / "r.parquet", ro, edit_x or (lambda c: None))
        _edit_long(S / "r.F.parquet", case / "r.F.parquet", edit_F or (lambda c: None))
        bad = case / ("r.F.parquet" if edit_F else "r.parquet")
        refuse("render", "ply", "--asset", S / "pillow.ply", "--scene", S / "pillow.scene.npz", "--rollout", ro,
               "--frames", "0", "-o", case / "out", names=(bad,), says=(says,))


def test_a_library_that_cannot_tell_candidates_apart_is_refused_or_flagged(refuse, tmp_path, rng, capsys):
    q = _queries(tmp_path / "q.csv", rng)
    same = _library(tmp_path / "same.csv", np.tile(rng.uniform(0.1, 1.0, 5), (12, 1)))
    cal = ("calibrate", "--method", "local_ridge", "--queries", q, "--output", tmp_path / "est.json")
    refuse(*cal, "--library", same, names=("same.csv", "features"), says=("degenerate",))
    good = _library(tmp_path / "good.csv", rng.uniform(0.1, 1.0, (12, 5)))
    refuse(*cal, "--library", good, "--k", "1000", names=("good.csv", "'k'"), says=("12 candidates",))
    one = _library(tmp_path / "one.csv", rng.uniform(0.1, 1.0, (1, 5)))
    refuse(*cal, "--library", one, "--k", "10", names=("one.csv", "'k'"))
    # descriptors along one direction only: used, flagged on stderr and in the estimate
    line = _library(tmp_path / "line.csv", np.outer(np.linspace(0.2, 1.0, 12), rng.uniform(0.5, 1.0, 5)))
    assert main(["calibrate", "--method", "local_ridge", "--queries", str(q), "--library", str(line),
                 "--output", str(tmp_path / "est.json")]) == 0
    err = capsys.readouterr().err
    assert "degenerate library design" in err and "Traceback" not in err, err
    assert "degenerate" in json.loads((tmp_path / "est.json").read_text())["library"]


def test_a_contract_asking_for_more_memory_than_exists_is_refused_before_allocating(refuse, tmp_path):
    text = (ROOT / "config/objects/pillow.yaml").read_text()
    cfg = tmp_path / "cfg"
    shutil.copytree(ROOT / "config", cfg, ignore=shutil.ignore_patterns("*.bak"))
    cases = {"n_grid": ("n_grid: 32,", "n_grid: 4096,", "profiles.ci.n_grid"),
             "n_frames": ("n_frames: 31}", "n_frames: 1000000}", "n_frames")}
    for name, (old, new, field) in cases.items():
        assert old in text, old
        (cfg / "objects/pillow.yaml").write_text(text.replace(old, new, 1))
        refuse("simulate", "--object", "pillow", "--config-dir", cfg, "--profile", "ci", "--probe", "standard_x",
               "--quiet", "-o", tmp_path / "x.parquet", names=("pillow.yaml", field), says=("GB", "at most"))


def test_an_option_that_parses_but_means_nothing_is_refused(shared, refuse, tmp_path):
    frames = tmp_path / "f.npz"
    frames.write_bytes(b"")
    tr = ("observe", "tracks", frames, "-o", tmp_path / "t.parquet")
    refuse(*tr, "--radius", "-3", names=("--radius",), says=("> 0",))
    refuse(*tr, "--seed", "-1", names=("--seed",))
    refuse(*tr, "--probe", "standard_x", names=("--probe",), says=("--object",))
    refuse("simulate", "--object", "pillow", "--profile", "ci", "--probe", "standard_x", "--theta", "1,1e-320",
           "-o", tmp_path / "x.parquet", names=("--theta",))


def test_a_workflow_table_that_leaks_a_target_is_refused_when_read(tmp_path):
    from knockgs_core.contract import check_held_out, read_yaml
    from knockgs_core.errors import InputError

    cand = ROOT / "config/candidates.csv"
    targets = (ROOT / "config/targets.csv").read_text()
    first = next(r for r in cand.read_text().splitlines() if r and not r.startswith(("#", "case_name")))
    _, se, sr = first.split(",")[:3]
    leaked = tmp_path / "leaked.csv"
    leaked.write_text(targets + f"alt_3,leak_1,{se},{sr}\n")
    with pytest.raises(InputError, match="is the candidate"):
        check_held_out(cand, leaked)
    twice = tmp_path / "twice.csv"
    row = next(r for r in targets.splitlines() if r.startswith("main,"))
    twice.write_text(targets + row.replace(row.split(",")[1], "again", 1) + "\n")
    with pytest.raises(InputError, match="repeats the parameter pair"):
        check_held_out(cand, twice)
    dup = tmp_path / "dup.yaml"
    dup.write_text("profile: ci\ndraws: 30\ndraws: 31\n")
    with pytest.raises(InputError, match="duplicate key 'draws'"):
        read_yaml(dup)


# --------------------------------------------------------------------------- 4. errors naming the right thing


def _rgbd(path: Path, **override) -> Path:
    w, h, t = 8, 6, 3
    fields = dict(rgb=np.zeros((t, h, w, 3), np.float16), alpha=np.zeros((t, h, w), np.float16),
                  depth=np.zeros((t, h, w), np.float32), intrinsics=np.array([w, h, 10.0, 10.0, 4.0, 3.0]),
                  world_to_camera=np.eye(4), frame_dt=np.float64(0.02))
    fields.update(override)
    np.savez(path, **fields)
    return path


def test_a_bad_field_deep_in_a_file_is_named_by_the_file(shared, refuse, tmp_path):
    cases = {
        "nan": ({"intrinsics": np.array([8, 6, np.nan, 10.0, 4.0, 3.0])}, "intrinsics"),
        "dt": ({"frame_dt": np.array([0.02, 0.02])}, "frame_dt"),
        "pose": ({"world_to_camera": np.eye(3)}, "world_to_camera"),
        "fx": ({"intrinsics": np.array([8, 6, 0.0, 10.0, 4.0, 3.0])}, "intrinsics"),
    }
    for name, (override, field) in cases.items():
        f = _rgbd(tmp_path / f"{name}.npz", **override)
        refuse("observe", "tracks", f, "-o", tmp_path / f"{name}.parquet", names=(f"{name}.npz", field))
    S = shared  # particles moved out of the domain: the particle file is named, not a probe box
    z = dict(np.load(S / "pillow.particles.npz"))
    for name, x in {"x10": z["positions"] * 10, "point": np.ones_like(z["positions"])}.items():
        f = tmp_path / f"{name}.particles.npz"
        np.savez(f, **{**z, "positions": x})
        refuse("simulate", "--object", "pillow", "--profile", "ci", "--probe", "standard_x", "--particles", f,
               "-o", tmp_path / "x.parquet", names=(f"{name}.particles.npz", "positions"))


def test_a_programming_error_is_one_line_that_names_the_inputs_and_is_never_hidden(tmp_path, rng, capsys,
                                                                                    monkeypatch):
    import knockgs_core.calibration as calibration

    lib = _library(tmp_path / "lib.csv", rng.uniform(0.1, 1.0, (12, 5)))
    q = _queries(tmp_path / "q.csv", rng)
    args = ["calibrate", "--method", "local_ridge", "--library", str(lib), "--queries", str(q),
            "--output", str(tmp_path / "e.json")]
    for exc in (TypeError("unsupported operand"), RuntimeError("Warp kernel failed")):
        def boom(*a, _exc=exc, **k):
            raise _exc
        monkeypatch.setattr(calibration, "calibrate", boom)
        assert main(args) == 1
        err = capsys.readouterr().err
        lines = err.strip().splitlines()
        assert len(lines) == 1 and "Traceback" not in err, err
        for text in ("internal error", type(exc).__name__, str(exc), "lib.csv", "KNOCKGS_TRACEBACK=1"):
            assert text in lines[0], (text, lines[0])
        monkeypatch.setenv("KNOCKGS_TRACEBACK", "1")
        with pytest.raises(type(exc)):
            main(args)
        monkeypatch.delenv("KNOCKGS_TRACEBACK")
    assert sorted(os.listdir(tmp_path)) == ["lib.csv", "q.csv"]


def test_a_bad_workflow_config_is_one_line_naming_the_file_and_key(tmp_path):
    """Snakemake stops at config read (a dry run), with one line: the file, the key, what is
    allowed; no schema dump, no stack. The two runs go together (Snakemake's start is most of
    their time)."""
    env = {**os.environ, "PYTHONPATH": str(ROOT / "src")}
    cases = {"dup.yaml": ("profile: ci\ndraws: 30\ndraws: 31\n", ("dup.yaml", "duplicate key 'draws'")),
             "unknown.yaml": ("profile: ci\ndrawz: 30\n", ("unknown.yaml", "'drawz'", "allowed keys"))}
    runs = {}
    for name, (text, _) in cases.items():
        (tmp_path / name).write_text(text)
        runs[name] = subprocess.Popen(["snakemake", "-n", "--cores", "1", "-q", "--configfile", str(tmp_path / name)],
                                      cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env)
    for name, (_, says) in cases.items():
        out, _ = runs[name].communicate(timeout=120)
        err = [line for line in out.splitlines() if line.strip() and not line.startswith("Config file ")]
        assert runs[name].returncode == 1 and len(err) == 1, out
        assert "Traceback" not in out and all(s in err[0] for s in says), err[0]

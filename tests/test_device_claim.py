"""A GPU of each process's own under the device name "cuda" (knockgs_core._device_claim):
processes that claim together get different cards, a card is free again once its process
ends however it ends, a process waits (or times out) while every card is held."""

import os
import signal
import subprocess
import sys
import textwrap

import pytest

from knockgs_core import _device_claim
from knockgs_core._device_claim import claim_slot, default_lock_dir, release_all
from knockgs_core._warp import resolve_device, warp_device
from knockgs_core.errors import InputError

pytestmark = pytest.mark.skipif(_device_claim.fcntl is None, reason="claims need POSIX file locks")

# a process that claims one of the cards, prints its index, and holds it until its stdin closes
HOLDER = textwrap.dedent("""
    import sys
    from knockgs_core._device_claim import claim_slot
    keys = sys.argv[2].split(",")
    try:
        i = claim_slot(keys, lock_dir=sys.argv[1], wait_s=float(sys.argv[3]), poll_s=0.05)
    except TimeoutError as exc:
        print("timeout", exc, flush=True)
        raise SystemExit(0)
    print(i, flush=True)
    sys.stdin.read()
""")


def _holder(lock_dir, keys, wait_s=5.0):
    proc = subprocess.Popen([sys.executable, "-c", HOLDER, str(lock_dir), ",".join(keys), str(wait_s)],
                            stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    return proc, proc.stdout.readline().strip()


def _end(proc):
    proc.stdin.close()
    proc.wait(timeout=30)


def test_processes_claiming_together_get_different_cards_and_a_third_waits(tmp_path):
    keys = ["GPU-aaaa", "GPU-bbbb"]
    a, ia = _holder(tmp_path, keys)
    b, ib = _holder(tmp_path, keys)
    try:
        assert sorted([ia, ib]) == ["0", "1"]
        c, out = _holder(tmp_path, keys, wait_s=0.3)
        assert out.startswith("timeout") and "2 GPUs are held" in out
        c.wait(timeout=30)
        # the first holder ends: its card is the one the next process gets
        _end(a)
        d, idd = _holder(tmp_path, keys)
        assert idd == ia
        _end(d)
    finally:
        for proc in (a, b):
            if proc.poll() is None:
                _end(proc)


def test_a_killed_process_frees_its_card(tmp_path):
    keys = ["GPU-only"]
    a, ia = _holder(tmp_path, keys)
    assert ia == "0"
    os.kill(a.pid, signal.SIGKILL)
    a.wait(timeout=30)
    b, ib = _holder(tmp_path, keys, wait_s=2.0)
    assert ib == "0"
    _end(b)


def test_a_waiting_process_takes_the_card_once_it_is_freed(tmp_path):
    keys = ["GPU-only"]
    a, _ = _holder(tmp_path, keys)
    waiter = subprocess.Popen([sys.executable, "-c", HOLDER, str(tmp_path), ",".join(keys), "20"],
                              stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    _end(a)
    assert waiter.stdout.readline().strip() == "0"
    _end(waiter)


def test_a_process_keeps_its_claim_and_cards_are_named_safely(tmp_path):
    try:
        keys = ["00000000:1A:00", "00000000:1B:00"]
        first = claim_slot(keys, lock_dir=tmp_path)
        assert claim_slot(keys, lock_dir=tmp_path) == first == 0
        names = sorted(p.name for p in tmp_path.iterdir())
        assert names == ["gpu-00000000_1A_00.lock"]
        # another process sees the card held and takes the other one
        other, i = _holder(tmp_path, keys)
        assert i == "1"
        _end(other)
        with pytest.raises(ValueError):
            claim_slot([], lock_dir=tmp_path)
    finally:
        release_all()


def test_a_lock_folder_that_cannot_be_made_is_one_clear_error(tmp_path):
    (tmp_path / "file").write_text("not a folder")
    with pytest.raises(InputError, match="KNOCKGS_GPU_LOCKS") as err:
        claim_slot(["GPU-x"], lock_dir=tmp_path / "file" / "locks")
    assert "file/locks" in str(err.value) and "\n" not in str(err.value)


def test_the_lock_folder_follows_the_environment(tmp_path, monkeypatch):
    monkeypatch.setenv(_device_claim.LOCKS_ENV, str(tmp_path / "locks"))
    assert default_lock_dir() == tmp_path / "locks"
    monkeypatch.delenv(_device_claim.LOCKS_ENV)
    assert default_lock_dir().name.startswith("knockgs-gpu-locks-")


def test_device_names_resolve_and_cuda_without_a_gpu_is_one_clear_error():
    assert resolve_device("cpu") == "cpu"
    assert resolve_device(" cpu ") == "cpu"
    assert warp_device("cpu").alias == "cpu"
    import warp as wp

    if wp.get_cuda_device_count() > 0:
        assert resolve_device("cuda").startswith("cuda:")
        assert resolve_device("cuda") == resolve_device("cuda")
    else:
        with pytest.raises(InputError, match="'cuda' is not available") as err:
            warp_device("cuda")
        assert "\n" not in str(err.value)

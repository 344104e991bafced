"""Issue 27: the temporary files of a killed save are removed by the next save of the same
target (and only those: a live writer's, another host's and another target's stay), and the
folder swap recovers from a kill between its two renames."""

import os
import shutil
import subprocess
import sys
import time

import numpy as np

from dolfinx_lopinf.core import io_atomic


def _dead_pid() -> int:
    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait()
    return proc.pid


def test_killed_saves_leave_nothing_behind_after_the_next_save(tmp_path):
    path = io_atomic.atomic_savez(tmp_path / "rom", K=np.eye(2))
    host = io_atomic._host()
    dead = tmp_path / f".rom.npz.{host}-{_dead_pid()}.ab12cd34.tmp"  # a save that was killed
    dead.write_bytes(b"\0" * 16_000_000)  # 16 MB, as for a model
    live = tmp_path / f".rom.npz.{host}-{os.getpid()}.zz99yy88.tmp"  # a save in progress
    live.write_bytes(b"partial")
    remote = tmp_path / f".rom.npz.otherhost-{_dead_pid()}.ab12cd34.tmp"  # another host's
    remote.write_bytes(b"?")
    other = tmp_path / f".snaps.npz.{host}-{_dead_pid()}.ab12cd34.tmp"  # another target's
    other.write_bytes(b"?")
    old = tmp_path / ".rom.npz.k3j4h5g6.tmp"  # untagged (an older version's), an hour old
    old.write_bytes(b"old")
    young = tmp_path / ".rom.npz.q1w2e3r4.tmp"  # untagged, just written
    young.write_bytes(b"young")
    hour_ago = time.time() - io_atomic.LEGACY_TEMPORARY_AGE - 60
    os.utime(old, (hour_ago, hour_ago))
    assert sorted(io_atomic.stale_temporaries(tmp_path, "rom.npz")) == sorted([dead, old])
    io_atomic.atomic_savez(path, K=2 * np.eye(2))
    assert sorted(os.listdir(tmp_path)) == sorted(p.name for p in (path, live, remote, other, young))
    with np.load(path) as data:
        assert data["K"][0, 0] == 2.0


def test_a_temporary_is_named_after_its_target_and_owner(tmp_path):
    seen = []

    def write(f):
        seen.extend(n for n in os.listdir(tmp_path) if n.endswith(".tmp"))
        f.write(b"x")

    io_atomic.atomic_write(tmp_path / "m.json", write)
    assert len(seen) == 1 and seen[0].startswith(f".m.json.{io_atomic._host()}-{os.getpid()}.")
    assert seen[0].endswith(".tmp")


def test_swap_folder_and_its_recovery(tmp_path, monkeypatch):
    target, new = tmp_path / "a.bp", tmp_path / "new"
    target.mkdir()
    (target / "old").write_text("1")
    new.mkdir()
    (new / "fresh").write_text("2")
    io_atomic.swap_folder(new, target)
    assert os.listdir(target) == ["fresh"]
    if new.exists():  # exchanged: the old version is where the new one was
        assert os.listdir(new) == ["old"]
    # a file system that cannot exchange, killed between the two renames: recoverable
    monkeypatch.setattr(io_atomic, "_exchange", lambda a, b: False)
    parked = tmp_path / ".a.bp.previous"
    os.replace(target, parked)  # what the first rename did before the kill
    assert not target.exists()
    assert "restored" in io_atomic.recover_folder(target)
    assert os.listdir(target) == ["fresh"] and not parked.exists()
    parked.mkdir()  # killed after the second rename: the parked old version is deleted
    assert "removed" in io_atomic.recover_folder(target)
    assert not parked.exists() and io_atomic.recover_folder(target) is None
    shutil.rmtree(new, ignore_errors=True)
    new.mkdir()
    (new / "third").write_text("3")
    io_atomic.swap_folder(new, target)  # the two-step swap itself
    assert os.listdir(target) == ["third"] and not parked.exists()

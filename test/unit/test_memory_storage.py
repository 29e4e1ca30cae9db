"""Durability: WAL replay after a crash, torn records, snapshots (round trip, corruption)."""
import glob
import json
import os

import numpy as np
import pytest

from comper_memory.core import CompactMemory, MemoryConfig, SnapshotError
from comper_msgs_py.arrays import Transitions


def make(rng, n, obs=(6, 6)):
    return Transitions(rng.integers(0, 256, (n,) + obs, dtype=np.uint8), rng.integers(0, 18, n),
                       rng.standard_normal(n).astype(np.float32),
                       rng.integers(0, 256, (n,) + obs, dtype=np.uint8),
                       rng.random(n) < 0.1, np.zeros(n, bool),
                       value_labels=rng.standard_normal(n).astype(np.float32))


def assert_same_state(a, b):
    (xa, ma), (xb, mb) = a.export_state(), b.export_state()
    assert ma == mb
    assert sorted(xa) == sorted(xb)
    for k in xa:
        np.testing.assert_array_equal(xa[k], xb[k], err_msg=k)
    sa, sb = a.stats(), b.stats()
    sa.pop("bytes_used"), sb.pop("bytes_used"), sa.pop("leases"), sb.pop("leases")
    assert sa == sb


def workload(mem, rng, steps=6):
    pool = make(rng, 30)
    for i in range(steps):
        mem.store(Transitions.concatenate([make(rng, 10), pool.take(rng.integers(0, 30, 10))]))
        if i % 2:
            mem.reduce(max_sets=7)


def test_wal_replay_after_crash_equals_state(tmp_path):
    cfg = MemoryConfig(storage_dir=str(tmp_path), snapshot_every=0, history_length=4)
    mem = CompactMemory(cfg)
    workload(mem, np.random.default_rng(0))
    # "SIGKILL": no close(); the flushed WAL is all that is left
    again = CompactMemory(cfg)
    assert_same_state(mem, again)
    # the replayed memory keeps working and logging
    workload(again, np.random.default_rng(1), steps=2)
    again.close()
    third = CompactMemory(cfg)
    assert_same_state(again, third)


def test_torn_last_record_is_ignored(tmp_path):
    cfg = MemoryConfig(storage_dir=str(tmp_path), snapshot_every=0)
    mem = CompactMemory(cfg)
    rng = np.random.default_rng(2)
    mem.store(make(rng, 5))
    state_after_first = mem.export_state()
    mem.store(make(rng, 5))
    del mem  # killed (no close(): a clean stop would record the second record as acknowledged)
    (wal,) = glob.glob(os.path.join(tmp_path, "wal-*.log"))
    size = os.path.getsize(wal)
    with open(wal, "r+b") as f:
        f.truncate(size - 17)  # killed in the middle of writing the second record
    again = CompactMemory(cfg)
    arrays, meta = again.export_state()
    for k, v in state_after_first[0].items():
        np.testing.assert_array_equal(arrays[k], v)
    assert again.stats()["identities"] == 5 and again.stats()["wal_sequence"] == 1
    again.store(make(rng, 3))  # appends after the repaired tail
    again.close()
    assert CompactMemory(cfg).stats()["identities"] == 8


def test_corrupt_complete_last_record_is_refused_unless_loss_accepted(tmp_path):
    """A complete record whose CRC fails was written in full, so it was acknowledged: not a torn
    write. Start-up refuses it (file unchanged) until wal_accept_loss says to drop it."""
    cfg = MemoryConfig(storage_dir=str(tmp_path), snapshot_every=0)
    mem = CompactMemory(cfg)
    rng = np.random.default_rng(3)
    mem.store(make(rng, 4))
    mem.store(make(rng, 4))
    mem.close()
    (wal,) = glob.glob(os.path.join(tmp_path, "wal-*.log"))
    with open(wal, "r+b") as f:
        f.seek(-5, os.SEEK_END)
        f.write(b"\xff")
    damaged = open(wal, "rb").read()
    with pytest.raises(SnapshotError, match="wal_accept_loss"):
        CompactMemory(cfg)
    assert open(wal, "rb").read() == damaged
    again = CompactMemory(MemoryConfig(storage_dir=str(tmp_path), snapshot_every=0, wal_accept_loss=True))
    assert again.stats()["identities"] == 4
    assert len(glob.glob(os.path.join(tmp_path, "wal-*.log.damaged-*"))) == 1


def test_periodic_snapshot_and_rotation(tmp_path):
    cfg = MemoryConfig(storage_dir=str(tmp_path), snapshot_every=3)
    mem = CompactMemory(cfg)
    workload(mem, np.random.default_rng(4), steps=8)
    assert os.path.exists(tmp_path / "snapshot" / "manifest.json")
    assert len(glob.glob(os.path.join(tmp_path, "wal-*.log"))) == 1
    again = CompactMemory(cfg)
    assert_same_state(mem, again)


def test_snapshot_round_trip(tmp_path):
    mem = CompactMemory(MemoryConfig(history_length=3))
    workload(mem, np.random.default_rng(5))
    lease = mem.begin_reduce(4)  # leased sets go back to TM in the snapshot
    mem.save_snapshot(str(tmp_path / "snap"))
    other = CompactMemory(MemoryConfig(history_length=3))
    other.load_snapshot(str(tmp_path / "snap"))
    assert other.tm_size == mem.tm_size + len(lease)
    mem.commit_reduce(lease.reduction_id, lease.identity_ids, np.zeros(len(lease)))
    mem.save_snapshot(str(tmp_path / "snap"))
    other.load_snapshot(str(tmp_path / "snap"))
    assert_same_state(mem, other)
    np.testing.assert_array_equal(mem.sample(5, seed=1).identity_ids, other.sample(5, seed=1).identity_ids)
    rng = np.random.default_rng(6)
    t = make(rng, 10)
    np.testing.assert_array_equal(mem.store(t).identity_ids, other.store(t).identity_ids)
    assert not any("pickle" in open(p, "rb").read().decode("latin1")
                   for p in glob.glob(str(tmp_path / "snap" / "*")))


@pytest.mark.parametrize("damage", ["truncate", "flip", "manifest", "missing"])
def test_corrupt_snapshot_refused(tmp_path, damage):
    mem = CompactMemory(MemoryConfig())
    workload(mem, np.random.default_rng(7))
    path = tmp_path / "snap"
    mem.save_snapshot(str(path))
    npz = path / "state.npz"
    if damage == "truncate":
        data = npz.read_bytes()
        npz.write_bytes(data[: len(data) // 2])
    elif damage == "flip":
        data = bytearray(npz.read_bytes())
        data[len(data) // 3] ^= 0x40
        npz.write_bytes(bytes(data))
    elif damage == "manifest":
        m = json.loads((path / "manifest.json").read_text())
        (path / "manifest.json").write_text(json.dumps(m)[:-10])
    else:
        npz.unlink()
    other = CompactMemory(MemoryConfig())
    rng = np.random.default_rng(8)
    other.store(make(rng, 3))
    before = other.export_state()
    with pytest.raises(SnapshotError):
        other.load_snapshot(str(path))
    after = other.export_state()
    assert before[1] == after[1]
    for k in before[0]:
        np.testing.assert_array_equal(before[0][k], after[0][k])

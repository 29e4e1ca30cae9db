"""Memory hardening (issue 16), core level: damaged WAL records, snapshot metadata and replacement
rules, kills at every step of a checkpoint, commit order, bounded key values, the index's cost
under drifting and poisoned keys, and property-based fuzzing of every request.

Costs are asserted as counts (candidate pairs scanned, index rebuilds), never as times."""
from __future__ import annotations

import glob
import json
import os

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from comper_memory.core import CompactMemory, MemoryConfig, MemoryInputError, SnapshotError
from comper_memory.core import storage as storage_mod
from comper_msgs_py.arrays import Transitions


def make(rng, n, obs=6, act=2, drift_from=None):
    s = rng.standard_normal((n, obs)).astype(np.float32)
    s2 = rng.standard_normal((n, obs)).astype(np.float32)
    if drift_from is not None:  # a step counter in the observation
        s[:, 0] = drift_from + np.arange(n, dtype=np.float32)
        s2[:, 0] = s[:, 0] + 1
    return Transitions(s, rng.uniform(-1, 1, (n, act)).astype(np.float32),
                       rng.standard_normal(n).astype(np.float32), s2, np.zeros(n, bool), np.zeros(n, bool),
                       value_labels=rng.standard_normal(n).astype(np.float32))


def state_of(mem):
    arrays, meta = mem.export_state()
    s = mem.stats()
    for k in ("bytes_used", "leases"):
        s.pop(k)
    return arrays, meta, s


def assert_same(a, b):
    xa, ma, sa = a
    xb, mb, sb = b
    assert ma == mb and sa == sb and sorted(xa) == sorted(xb)
    for k in xa:
        np.testing.assert_array_equal(xa[k], xb[k], err_msg=k)


def filled(tmp_path, n_ops=50, close=True, **kw):
    cfg = MemoryConfig(storage_dir=str(tmp_path), snapshot_every=0, **kw)
    mem = CompactMemory(cfg)
    rng = np.random.default_rng(0)
    for i in range(n_ops):
        mem.store(make(rng, 4))
    if close:   # a clean stop (its mark says every record was acknowledged); else a kill
        mem.close()
    (wal,) = glob.glob(os.path.join(tmp_path, "wal-*.log"))
    return cfg, wal


def record_offsets(wal):
    data = open(wal, "rb").read()
    offs, off = [], 0
    while off < len(data):
        offs.append(off)
        _, length, _ = storage_mod._HEAD.unpack_from(data, off)
        off += storage_mod._HEAD.size + length
    return offs


# ----------------------------------------------------------------------------- WAL replay (2)
@pytest.mark.parametrize("where", ["first_byte", "crc_at_20_percent"])
def test_corrupt_wal_record_in_the_middle_stops_start_up(tmp_path, where):
    """Issue 16 failure 2: a flipped byte at 20 % lost 40 of 50 operations silently, a flipped
    first byte emptied the WAL. Now start-up stops with the offset, the records after it and the
    parameter that accepts the loss; the file is not changed."""
    cfg, wal = filled(tmp_path)
    offs = record_offsets(wal)
    k = 0 if where == "first_byte" else 10
    raw = bytearray(open(wal, "rb").read())
    pos = offs[k] if where == "first_byte" else offs[k] + storage_mod._HEAD.size + 20
    raw[pos] ^= 0xFF
    open(wal, "wb").write(bytes(raw))
    with pytest.raises(SnapshotError) as err:
        CompactMemory(cfg)
    msg = str(err.value)
    assert f"byte offset {offs[k]}" in msg and f"{49 - k} intact records follow" in msg, msg
    assert "wal_accept_loss:=true" in msg
    assert err.value.offset == offs[k] and err.value.records_after == 49 - k
    assert open(wal, "rb").read() == bytes(raw), "the damaged file must stay as it was"
    # accepting the loss explicitly: every intact record (a record whose header alone is damaged too; the one
    # whose payload fails its CRC is dropped), a copy of the damaged file, a warning
    warnings = []
    mem = CompactMemory(MemoryConfig(storage_dir=str(tmp_path), snapshot_every=0, wal_accept_loss=True),
                        log=warnings.append)
    kept = 50 if where == "first_byte" else 49
    assert mem.stats()["wal_sequence"] == 50 and mem.stats()["identities"] == 4 * kept
    (copy,) = glob.glob(wal + ".damaged-*")
    assert open(copy, "rb").read() == bytes(raw)
    assert any("wal_accept_loss" in w and str(offs[k]) in w for w in warnings), warnings
    mem.store(make(np.random.default_rng(9), 3))  # and it keeps logging
    mem.close()
    assert CompactMemory(cfg).stats()["wal_sequence"] == 51


def test_torn_tail_is_dropped_with_a_warning(tmp_path):
    cfg, wal = filled(tmp_path, n_ops=5, close=False)
    size = os.path.getsize(wal)
    with open(wal, "r+b") as f:
        f.truncate(size - 11)   # killed while writing the last record: never acknowledged
    warnings = []
    mem = CompactMemory(cfg, log=warnings.append)
    assert mem.stats()["wal_sequence"] == 4
    assert len(warnings) == 1 and "torn" in warnings[0] and "never acknowledged" in warnings[0]
    mem.close()
    assert CompactMemory(cfg, log=warnings.append).stats()["wal_sequence"] == 4 and len(warnings) == 1


def test_torn_tail_of_an_older_log_file_is_corruption(tmp_path):
    """Only the last file may end in a torn record: records after it elsewhere would be lost."""
    cfg, wal = filled(tmp_path, n_ops=5)
    with open(wal, "r+b") as f:
        f.truncate(os.path.getsize(wal) - 11)
    later = os.path.join(tmp_path, "wal-9999999999999999.log")
    with open(later, "wb") as f:
        f.write(storage_mod.encode_arrays(6, storage_mod.WAL_COMMIT, {"x": np.zeros(1)}))
    with pytest.raises(SnapshotError, match="1 more records are in 1 later log files"):
        CompactMemory(cfg)


# ----------------------------------------------------------------------------- snapshots (1, 5, 8)
def test_manifest_is_covered_by_the_checksum(tmp_path):
    """Issue 16 failure 5: lowering next_id in manifest.json started silently and handed out
    identity ids that existed already."""
    mem = CompactMemory(MemoryConfig())
    mem.store(make(np.random.default_rng(1), 20))
    path = tmp_path / "snap"
    mem.save_snapshot(str(path))
    m = json.loads((path / "manifest.json").read_text())
    m["meta"]["counters"]["next_id"] = 3
    (path / "manifest.json").write_text(json.dumps(m))
    with pytest.raises(SnapshotError, match="manifest.json checksum"):
        CompactMemory(MemoryConfig()).load_snapshot(str(path))
    # a format-1 manifest (no manifest checksum) with the same edit: refused by the consistency check
    m.pop("manifest_sha256", None)
    m["format"] = 1
    (path / "manifest.json").write_text(json.dumps(m))
    with pytest.raises(SnapshotError, match="next_id"):
        CompactMemory(MemoryConfig()).load_snapshot(str(path))


def test_snapshot_never_replaces_what_is_not_a_snapshot(tmp_path):
    """Issue 16 failure 1 (core part): a save replaced whatever was at the path."""
    mem = CompactMemory(MemoryConfig())
    mem.store(make(np.random.default_rng(2), 5))
    other = tmp_path / "project"
    other.mkdir()
    (other / "notes.txt").write_text("keep me")
    with pytest.raises(SnapshotError, match="not a snapshot directory"):
        mem.save_snapshot(str(other))
    assert (other / "notes.txt").read_text() == "keep me" and sorted(os.listdir(tmp_path)) == ["project"]
    afile = tmp_path / "file.bin"
    afile.write_bytes(b"data")
    with pytest.raises(SnapshotError, match="not a snapshot directory"):
        mem.save_snapshot(str(afile))
    assert afile.read_bytes() == b"data" and sorted(os.listdir(tmp_path)) == ["file.bin", "project"]
    mem.save_snapshot(str(tmp_path / "snap"))       # a new snapshot, then replacing it, is fine
    mem.save_snapshot(str(tmp_path / "snap"))
    assert sorted(os.listdir(tmp_path / "snap")) == ["manifest.json", "state.npz"]
    assert sorted(os.listdir(tmp_path)) == ["file.bin", "project", "snap"]


class _Killed(BaseException):
    """Stands for SIGKILL inside a checkpoint: nothing after it runs, nothing is cleaned up."""


def _fs_steps(monkeypatch, kill_at):
    """Count the file-system mutations of a checkpoint; 'die' at the kill_at-th one."""
    count = [0]
    for name in ("rename", "remove", "rmdir", "makedirs"):
        real = getattr(os, name)

        def wrapped(*a, _real=real, **k):
            count[0] += 1
            if count[0] == kill_at:
                raise _Killed()
            return _real(*a, **k)
        monkeypatch.setattr(os, name, wrapped)
    return count


def test_kill_at_every_step_of_a_checkpoint_leaves_a_startable_state(tmp_path, monkeypatch):
    """Issue 16 failure 8: a kill between the two renames left a state the node refused to start
    from (the good snapshot aside), and snapshot.old-<pid> could stay forever. Every file-system
    step of a checkpoint is 'killed' in turn; a new memory on the directory has every
    acknowledged operation and no leftovers."""
    rng = np.random.default_rng(3)
    batches = [make(rng, 6) for _ in range(8)]
    total = None
    kill_at = 1
    while True:
        d = tmp_path / f"k{kill_at}"
        cfg = MemoryConfig(storage_dir=str(d), snapshot_every=0)
        mem = CompactMemory(cfg)
        for b in batches[:4]:
            mem.store(b)
        mem.checkpoint()                      # a previous good snapshot exists
        for b in batches[4:]:
            mem.store(b)
        expected = state_of(mem)
        count = _fs_steps(monkeypatch, kill_at)
        killed = False
        try:
            mem.checkpoint()
        except _Killed:
            killed = True
        monkeypatch.undo()
        del mem                               # no close(): the process is gone
        again = CompactMemory(cfg)
        assert_same(state_of(again), expected)
        left = [n for n in os.listdir(d) if ".old-" in n or ".tmp-" in n]
        assert not left, (kill_at, left)
        again.store(batches[0])               # and it keeps working
        again.close()
        if not killed:
            total = count[0]
            break
        kill_at += 1
    assert total and total >= 4 and kill_at == total + 1


def test_restore_in_a_node_with_storage_keeps_the_log_position(tmp_path):
    """A restore is an operation at the current log position, so a kill after it never replays
    the replaced history over the restored state."""
    src = CompactMemory(MemoryConfig())
    src.store(make(np.random.default_rng(4), 5))
    src.save_snapshot(str(tmp_path / "snap"))
    cfg = MemoryConfig(storage_dir=str(tmp_path / "store"), snapshot_every=0)
    mem = CompactMemory(cfg)
    for _ in range(6):
        mem.store(make(np.random.default_rng(5), 7))
    seq = mem.stats()["wal_sequence"]
    mem.load_snapshot(str(tmp_path / "snap"))
    assert mem.stats()["wal_sequence"] == seq and mem.stats()["identities"] == 5
    expected = state_of(mem)
    del mem
    assert_same(state_of(CompactMemory(cfg)), expected)


# ----------------------------------------------------------------------------- reduce_commit order (7)
def test_commit_accepts_the_lease_ids_in_any_order():
    """Issue 16 failure 7: the docs and ReduceCommit.srv say any order; the core required the
    lease's order."""
    rng = np.random.default_rng(6)
    t = make(rng, 30)
    a, b = CompactMemory(MemoryConfig()), CompactMemory(MemoryConfig())
    a.store(t)
    b.store(t)
    la, lb = a.begin_reduce(10), b.begin_reduce(10)
    preds = np.arange(10, dtype=np.float32)
    perm = rng.permutation(10)
    a.commit_reduce(la.reduction_id, la.identity_ids, preds)
    b.commit_reduce(lb.reduction_id, lb.identity_ids[perm], preds[perm])
    assert_same(state_of(a), state_of(b))
    lease = b.begin_reduce(5)
    with pytest.raises(MemoryInputError, match="differ"):
        b.commit_reduce(lease.reduction_id, np.r_[lease.identity_ids[:4], lease.identity_ids[0]], np.zeros(5))


# ----------------------------------------------------------------------------- bounded keys (3, 4)
@pytest.mark.parametrize("value", [1e20, -3e9, 2e8])
def test_key_values_beyond_the_bound_are_refused_whole(value):
    """Issue 16 failure 3: one key value of 1e20 was accepted and slowed every later store."""
    mem = CompactMemory(MemoryConfig())
    mem.store(make(np.random.default_rng(7), 10))
    before = state_of(mem)
    bad = make(np.random.default_rng(8), 16)
    bad.next_states[11, 2] = np.float32(value)
    with pytest.raises(MemoryInputError, match=r"transition 11 .*next_state.*max_key_abs"):
        mem.store(bad)
    assert_same(state_of(mem), before)
    bad.next_states[11, 2] = np.float32(1e8)   # at the bound: accepted
    mem.store(bad)


def _scanned_per_transition(mem, batch):
    before = mem.index.scanned
    mem.store(batch)
    return (mem.index.scanned - before) / len(batch)


def _exact_checks_per_transition(mem, batch):
    """Candidates that pass the index's projected filter (each costs an exact float64 re-check)."""
    from comper_memory.core import transition_keys
    keys = transition_keys(batch)
    z = mem.index._zproj(keys)
    return sum(len(c) for _, c in mem.index.candidates_of(z)) / len(batch)


def test_poisoned_key_does_not_slow_later_stores():
    """A value at the bound stored first: later stores re-check and scan as few candidates as
    without it (before: its float32 rounding margin widened every candidate's filter radius and
    its extent stretched every cell, so each store re-checked every identity)."""
    costs = {}
    for poisoned in (False, True):
        rng = np.random.default_rng(10)
        mem = CompactMemory(MemoryConfig())
        if poisoned:
            p = make(rng, 1)
            p.states[0, 3] = np.float32(1e8)
            mem.store(p)
        for _ in range(12):
            mem.store(make(rng, 512))
        costs[poisoned] = [_exact_checks_per_transition(mem, make(rng, 64))]
        if hasattr(mem.index, "scanned"):
            costs[poisoned].append(np.mean([_scanned_per_transition(mem, make(rng, 64)) for _ in range(20)]))
    assert costs[True][0] <= 2 * costs[False][0] + 1, costs   # before: 6,144 (every identity)
    assert costs[True][1:] and costs[True][1] <= 2 * costs[False][1] + 1, costs


def test_drifting_keys_keep_a_bounded_cost_and_few_rebuilds():
    """Issue 16 failure 4: keys outside the fitted extent (a step counter) piled up in the grid's
    edge cells and the index rebuilt at nearly every store; a 16,384 batch took 26 s."""
    rng = np.random.default_rng(11)
    mem = CompactMemory(MemoryConfig())
    step = 0
    for _ in range(160):
        mem.store(make(rng, 64, drift_from=step))
        step += 64
    assert mem.index.rebuilds <= 12, mem.index.rebuilds
    cost = np.mean([_scanned_per_transition(mem, make(rng, 64, drift_from=step + 64 * i)) for i in range(20)])
    step += 64 * 20
    assert cost <= 30, cost
    big = make(rng, 16384, drift_from=step)
    assert _scanned_per_transition(mem, big) <= 30
    # exactness is kept: re-storing the big batch joins its own identities
    again = mem.store(big)
    assert again.new_identities == 0


# ----------------------------------------------------------------------------- fuzzing (8)
_dtypes = st.sampled_from([np.float32, np.float64, np.int64, np.uint8, np.int8, np.bool_])
_values = st.one_of(st.floats(allow_nan=True, allow_infinity=True, width=32),
                    st.sampled_from([0.0, 1e8, 1.1e8, -1e30, 3.4e38]))


@st.composite
def batches(draw):
    n = draw(st.integers(0, 6))
    obs = draw(st.sampled_from([(6,), (5,), (2, 3), ()]))
    act = draw(st.sampled_from([(n, 2), (n,), (n, 3), (n + 1, 2)]))
    sd = draw(_dtypes)
    s = np.zeros((n,) + obs, sd)
    s2 = np.zeros((n,) + obs, sd)
    if n and obs and draw(st.booleans()):
        with np.errstate(all="ignore"):
            s.flat[draw(st.integers(0, s.size - 1))] = draw(_values) if sd in (np.float32, np.float64) else 1
    labels_n = draw(st.sampled_from([n, 0, n + 1]))
    return Transitions(s, np.zeros(act, draw(_dtypes)), np.full(n, draw(_values), np.float32), s2,
                       np.zeros(n, bool), np.zeros(n, bool), value_labels=np.zeros(labels_n, np.float32))


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(ops=st.lists(st.one_of(
    st.tuples(st.just("store"), batches()),
    st.tuples(st.just("sample"), st.integers(-3, 40), st.sampled_from(["rtm", "tm", "x"]), st.integers(0, 3)),
    st.tuples(st.just("begin"), st.integers(-2, 8)),
    st.tuples(st.just("commit"), st.integers(0, 5), st.sampled_from(["exact", "reversed", "short", "dup", "nan"]))),
    max_size=12))
def test_fuzzed_requests_are_served_or_refused_without_change(ops):
    """Any request either succeeds or raises MemoryInputError with the state unchanged."""
    mem = CompactMemory(MemoryConfig(max_store_batch=8, max_sample_batch=32, history_length=4))
    mem.store(make(np.random.default_rng(12), 5))
    leases = {}
    for op in ops:
        before = state_of(mem)
        try:
            if op[0] == "store":
                mem.store(op[1])
            elif op[0] == "sample":
                mem.sample(op[1], op[2], seed=0, num_batches=op[3])
            elif op[0] == "begin":
                lease = mem.begin_reduce(op[1])
                leases[lease.reduction_id] = lease
            else:
                lease = leases.get(op[1])
                ids = lease.identity_ids if lease is not None else np.array([0, 1])
                preds = np.zeros(len(ids), np.float32)
                if op[2] == "reversed":
                    ids, preds = ids[::-1], preds[::-1]
                elif op[2] == "short":
                    ids, preds = ids[:-1], preds[:-1]
                elif op[2] == "dup" and len(ids):
                    ids = np.r_[ids[:-1], ids[0]]
                elif op[2] == "nan" and len(ids):
                    preds = np.full(len(ids), np.nan, np.float32)
                mem.commit_reduce(op[1], ids, preds)
        except MemoryInputError:
            after = state_of(mem)
            assert_same(after, before)

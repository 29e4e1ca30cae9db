"""Fault injection against memory_node in its own process (`ros2 run`), issue 16: SIGKILL at random
moments of a client that stores, reduces and snapshots (zero acknowledged loss over several
iterations), damaged WAL and snapshot metadata at start-up, snapshot path escapes, repeated
SIGTERMs, and property-based fuzzing of every service request with raw messages. Issue 57: a damaged
header of the last WAL record, a log emptied or cut below its mark, a flipped byte with
wal_accept_loss (every later record kept) and a torn tail (dropped, with a copy)."""
from __future__ import annotations

import json
import os
import random
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from comper_memory.client import MemoryServiceError
from comper_memory.core import CompactMemory, MemoryConfig
from comper_memory.core import storage as wal_format
from comper_msgs.msg import Array
from comper_msgs.srv import ReduceBegin, ReduceCommit, Sample, Snapshot, Store
from comper_msgs_py.convert import transitions_to_batch
from memory_worker import make_batch
from test_memory_node import client_of, refused, start  # noqa: F401 - fixture

HERE = Path(__file__).resolve().parent
WORKER = HERE / "memory_fault_worker.py"


def wait_exit(proc, timeout=30.0):
    try:
        return proc.proc.wait(timeout=timeout)
    except subprocess.TimeoutExpired:
        pytest.fail(f"{proc.name} did not exit:\n{proc.log()}")


def read_acks(path):
    if not path.exists():
        return []
    out = []
    for line in path.read_text().splitlines():
        try:
            out.append(json.loads(line))
        except ValueError:  # a line cut by the end of the worker cannot be an acknowledgement
            pass
    return out


def test_sigkill_during_store_reduce_and_snapshot_loses_nothing_acknowledged(launch, client_of, tmp_path):
    """Five SIGKILLs (MEMORY_FAULT_ITERATIONS) at random moments while a client stores, commits
    reductions (ids reversed) and writes checkpoints (snapshot_every 5 as well) and named
    snapshots: after each restart every acknowledged store maps to the same identities and every
    acknowledged commit is in RTM."""
    storage = tmp_path / "storage"
    params = ("-p", f"storage_dir:={storage}", "-p", "snapshot_every:=5", "-p", "key_size:=26")
    rnd = random.Random(int(os.environ.get("MEMORY_FAULT_SEED", "16")))
    all_stored = {}
    committed = {}
    for it in range(int(os.environ.get("MEMORY_FAULT_ITERATIONS", "5"))):
        proc, name = start(launch, f"kill{it}", *params)
        memory = client_of(name)
        s = memory.stats()
        assert s["identities"] >= sum(len(ids) for ids in all_stored.values()), (it, s)
        acks = tmp_path / f"acks{it}.jsonl"
        log = open(tmp_path / f"worker{it}.log", "wb")
        worker = subprocess.Popen([sys.executable, str(WORKER), "--node", name, "--worker", str(10 + it),
                                   "--ack-file", str(acks)], stdout=log, stderr=subprocess.STDOUT,
                                  env=os.environ.copy())
        try:
            target = rnd.randint(4, 40)
            deadline = time.monotonic() + 60
            while time.monotonic() < deadline and len(read_acks(acks)) < target:
                assert worker.poll() is None, (tmp_path / f"worker{it}.log").read_text()
                time.sleep(0.01)
            time.sleep(rnd.random() * 0.05)
            proc.kill(signal.SIGKILL)
            assert worker.wait(timeout=30) == 0
        finally:
            if worker.poll() is None:
                worker.kill()
            log.close()
        recs = read_acks(acks)
        assert len(recs) >= target
        for r in recs:
            if r["op"] == "store":
                all_stored[(10 + it, r["j"])] = r["ids"]
            elif r["op"] == "commit":
                committed.update(zip(r["ids"], r["preds"]))
    proc, name = start(launch, "kill_final", *params)
    memory = client_of(name)
    s = memory.stats()
    assert s["identities"] >= sum(len(ids) for ids in all_stored.values())
    assert committed, "no reduction was acknowledged"
    batch, rtm_ids, _ = memory.sample(s["rtm_size"], source="rtm", seed=0)
    got = dict(zip(rtm_ids.tolist(), batch.value_labels.tolist()))
    missing = [i for i in committed if i not in got]
    assert not missing, f"{len(missing)} acknowledged commits lost"
    assert all(got[i] == pytest.approx(p) for i, p in committed.items())
    for (w, j), ids in all_stored.items():  # every acknowledged transition is back, same identity
        reply = memory.store(make_batch(w, j, 16))
        assert reply.new_identities == 0 and reply.identity_ids.tolist() == ids, (w, j)
    proc.kill(signal.SIGTERM)
    assert proc.proc.returncode == 0, proc.log()
    assert not [n for n in os.listdir(storage) if ".old-" in n or ".tmp-" in n]


def _core_storage(path, ops=30):
    mem = CompactMemory(MemoryConfig(storage_dir=str(path), snapshot_every=0))
    for j in range(ops):
        mem.store(make_batch(1, j, 4))
    mem.close()
    (wal,) = sorted(path.glob("wal-*.log"))
    return wal


def record_offsets(wal):
    data, offs, off = wal.read_bytes(), [], 0
    while off < len(data):
        offs.append(off)
        off += wal_format._HEAD.size + wal_format._HEAD.unpack_from(data, off)[1]
    return offs


def flip(wal, pos, mask=0x01):
    raw = bytearray(wal.read_bytes())
    raw[pos] ^= mask
    wal.write_bytes(bytes(raw))
    return bytes(raw)


def test_damaged_wal_and_edited_manifest_stop_start_up_with_a_clear_error(launch, client_of, tmp_path):
    """A flipped byte at 20 % of the WAL (in the arrays of store 6 of 30): refused; with wal_accept_loss
    only that store is lost and every intact record after it is replayed (issue 57: all were dropped)."""
    storage = tmp_path / "storage"
    wal = _core_storage(storage)
    offs = record_offsets(wal)
    raw = flip(wal, offs[7] - 3)
    proc, _ = start(launch, "walbad", "-p", f"storage_dir:={storage}")
    assert wait_exit(proc) == 1
    log = proc.log()
    assert "cannot start" in log and "byte offset" in log and "23 intact records follow" in log, log
    assert "wal_accept_loss:=true" in log and "Traceback" not in log
    assert wal.read_bytes() == raw
    proc, name = start(launch, "walaccept", "-p", f"storage_dir:={storage}", "-p", "wal_accept_loss:=true")
    memory = client_of(name)
    assert memory.stats()["identities"] == 29 * 4
    log = proc.log()
    assert f"bytes {offs[6]}-{offs[7]}" in log and "dropped 1 logged operation (sequence 7)" in log, log
    assert (storage / f"{wal.name}.damaged-{offs[6]}").read_bytes() == raw
    for j in range(30):   # every store but the damaged one is back
        assert memory.store(make_batch(1, j, 4)).new_identities == (4 if j == 6 else 0), j
    assert proc.stop() == 0

    # a snapshot whose manifest was edited by hand (next_id lowered)
    storage2 = tmp_path / "storage2"
    mem = CompactMemory(MemoryConfig(storage_dir=str(storage2), snapshot_every=0))
    for j in range(5):
        mem.store(make_batch(2, j, 8))
    mem.checkpoint()
    mem.close()
    mpath = storage2 / "snapshot" / "manifest.json"
    m = json.loads(mpath.read_text())
    m["meta"]["counters"]["next_id"] = 1
    mpath.write_text(json.dumps(m))
    proc, _ = start(launch, "manifest", "-p", f"storage_dir:={storage2}")
    assert wait_exit(proc) == 1
    log = proc.log()
    assert "cannot start" in log and "manifest.json checksum" in log and "Traceback" not in log, log


def acked_storage(launch, tmp_path, tag, count, checkpoint_after=-1):
    """A node's storage after a worker process stored `count` batches of 16 (stores only, one WAL
    record each) and the node stopped cleanly (SIGTERM): (storage, {j: acknowledged identity ids})."""
    storage = tmp_path / tag
    proc, name = start(launch, tag, "-p", f"storage_dir:={storage}", "-p", "snapshot_every:=0",
                       "-p", "key_size:=26")
    acks = tmp_path / f"{tag}.jsonl"
    with open(tmp_path / f"{tag}_worker.log", "wb") as log:
        rc = subprocess.run([sys.executable, str(WORKER), "--node", name, "--worker", "3", "--ack-file", str(acks),
                             "--count", str(count), "--stores-only", "--checkpoint-after", str(checkpoint_after)],
                            stdout=log, stderr=subprocess.STDOUT, env=os.environ.copy(), timeout=120).returncode
    assert rc == 0, (tmp_path / f"{tag}_worker.log").read_text()
    proc.kill(signal.SIGTERM)
    assert proc.proc.returncode == 0, proc.log()
    stores = {r["j"]: r["ids"] for r in read_acks(acks) if r["op"] == "store"}
    assert sorted(stores) == list(range(count))
    return storage, stores


def assert_acked_stores_back(memory, stores, lost=()):
    """Each acknowledged store is back with the same identity ids; those in `lost` are not."""
    for j, ids in stores.items():
        reply = memory.store(make_batch(3, j, 16))
        if j in lost:
            assert reply.new_identities == 16, j
        else:
            assert reply.new_identities == 0 and reply.identity_ids.tolist() == ids, j


def test_a_damaged_header_of_the_last_record_is_refused_not_cut_as_a_torn_tail(launch, client_of, tmp_path):
    """Issue 57: after a clean stop, a flipped byte in the magic or the length field of the last
    record made it look torn; it was cut as "never acknowledged" and its 16 identities were lost.
    Now: refused (the payload checks out), kept with wal_accept_loss. Then a torn tail: after a
    SIGKILL the first bytes of a record are appended (the write a kill cut short): dropped with a
    warning and a copy, every acknowledged store back."""
    storage, stores = acked_storage(launch, tmp_path, "hdr", 12)
    for field, pos in (("length", 5), ("magic", 0)):
        d = tmp_path / f"hdr_{field}"
        shutil.copytree(storage, d)
        (wal,) = d.glob("wal-*.log")
        raw = flip(wal, record_offsets(wal)[-1] + pos)
        proc, _ = start(launch, f"hdr_{field}", "-p", f"storage_dir:={d}")
        assert wait_exit(proc) == 1
        log = proc.log()
        assert "cannot start" in log and "WalCorruptError" in log and "payload checks out" in log, log
        assert "accepting loses nothing" in log and "wal_accept_loss:=true" in log and "Traceback" not in log
        assert wal.read_bytes() == raw
    proc, name = start(launch, "hdr_accept", "-p", f"storage_dir:={d}", "-p", "wal_accept_loss:=true")
    memory = client_of(name)
    assert memory.stats()["identities"] == 12 * 16
    assert_acked_stores_back(memory, stores)
    assert "dropped 0 logged operations" in proc.log() and list(d.glob("wal-*.log.damaged-*"))
    memory.close()
    proc.kill(signal.SIGKILL)
    wal = sorted(d.glob("wal-*.log"))[-1]
    size = wal.stat().st_size
    torn = wal_format.encode_arrays(99, wal_format.WAL_STORE, {"states": np.zeros((16, 11), np.float32)})[:50]
    with open(wal, "ab") as f:
        f.write(torn)
    proc, name = start(launch, "hdr_torn", "-p", f"storage_dir:={d}")
    memory = client_of(name)
    assert_acked_stores_back(memory, stores)
    log = proc.log()
    assert "torn" in log and "never acknowledged" in log and "Traceback" not in log, log
    assert (d / f"{wal.name}.torn-{size}").read_bytes() == torn
    proc.kill(signal.SIGTERM)
    assert proc.proc.returncode == 0, proc.log()


def test_a_log_emptied_or_cut_below_its_mark_is_refused_at_start(launch, client_of, tmp_path):
    """Issue 57: a WAL emptied to 0 bytes after a checkpoint started without a word and lost every
    store after the checkpoint. wal.mark (written at start, checkpoint and clean stop) records the
    sequence the log reached; a log that ends before it is refused, naming the missing sequences."""
    storage, stores = acked_storage(launch, tmp_path, "cut", 12, checkpoint_after=3)  # snapshot at 4
    empty, cut = tmp_path / "cut_empty", tmp_path / "cut_cut"
    shutil.copytree(storage, empty)
    shutil.copytree(storage, cut)
    (wal,) = empty.glob("wal-*.log")
    wal.write_bytes(b"")
    proc, _ = start(launch, "cut_empty", "-p", f"storage_dir:={empty}")
    assert wait_exit(proc) == 1
    log = proc.log()
    assert "cannot start" in log and "WalMissingError" in log and "ends at sequence 4" in log, log
    assert "8 acknowledged operations (sequences 5-12) are missing" in log and "now 0 bytes" in log, log
    assert "wal_accept_loss:=true" in log and "Traceback" not in log and wal.stat().st_size == 0
    (wal,) = cut.glob("wal-*.log")
    with open(wal, "r+b") as f:
        f.truncate(record_offsets(wal)[5])   # at a record boundary: sequences 5-9 are left
    proc, _ = start(launch, "cut_cut", "-p", f"storage_dir:={cut}")
    assert wait_exit(proc) == 1
    log = proc.log()
    assert "3 acknowledged operations (sequences 10-12) are missing" in log and "Traceback" not in log, log
    proc, name = start(launch, "cut_accept", "-p", f"storage_dir:={cut}", "-p", "wal_accept_loss:=true")
    memory = client_of(name)
    assert memory.stats()["identities"] == 9 * 16 and "sequences 10-12" in proc.log()
    assert_acked_stores_back(memory, stores, lost=(9, 10, 11))
    proc.kill(signal.SIGTERM)
    assert proc.proc.returncode == 0, proc.log()


def test_snapshot_paths_are_confined_and_services_can_be_turned_off(launch, client_of, tmp_path):
    storage = tmp_path / "storage"
    proc, name = start(launch, "paths", "-p", f"storage_dir:={storage}", "-p", "snapshot_every:=0",
                       "-p", "snapshot_service:=save_restore")
    memory = client_of(name)
    acked = [memory.store(make_batch(4, j, 16)).identity_ids.tolist() for j in range(6)]
    victim = tmp_path / "victim"
    victim.mkdir()
    (victim / "data.txt").write_text("keep")
    outside = tmp_path / "outside"
    outside.mkdir()
    root = storage / "snapshots"
    root.mkdir()
    (root / "link").symlink_to(outside, target_is_directory=True)
    (root / "notsnap").mkdir()
    (root / "notsnap" / "x").write_text("keep")
    for path in ("../escape", "a/../../../escape", str(victim), str(storage), str(storage / "snapshot"),
                 str(tmp_path), "/", "link/inside", "link"):
        msg = refused(proc, lambda p=path: memory.snapshot(p), "snapshot")
        assert "outside snapshot_root" in msg or "symbolic link" in msg, (path, msg)
        msg = refused(proc, lambda p=path: memory.restore(p), "snapshot")
    refused(proc, lambda: memory.snapshot("notsnap"), "not a snapshot directory")
    assert (victim / "data.txt").read_text() == "keep" and (root / "notsnap" / "x").read_text() == "keep"
    assert sorted(os.listdir(outside)) == [] and not (tmp_path / "escape").exists()
    assert sorted(p.name for p in storage.iterdir() if p.name.startswith("wal-"))  # the live log is there
    path, _ = memory.snapshot("good")
    assert path == str(root / "good")
    memory.restore("good")
    # the live storage is intact: after a SIGKILL every acknowledged store is back
    proc.kill(signal.SIGKILL)
    proc2, name2 = start(launch, "paths2", "-p", f"storage_dir:={storage}", "-p", "snapshot_service:=save")
    memory = client_of(name2)
    for j, ids in enumerate(acked):
        assert memory.store(make_batch(4, j, 16)).identity_ids.tolist() == ids
    memory.snapshot("good")
    refused(proc2, lambda: memory.restore("good"), "restore is off")
    assert proc2.stop() == 0
    proc3, name3 = start(launch, "paths3", "-p", "snapshot_service:=disabled")
    memory = client_of(name3)
    refused(proc3, lambda: memory.snapshot(""), "snapshot_service disabled")
    refused(proc3, lambda: memory.restore("x"), "snapshot_service disabled")
    # a root that holds the live storage is refused at start
    proc4, _ = start(launch, "badroot", "-p", f"storage_dir:={storage}", "-p", f"snapshot_root:={tmp_path}")
    assert wait_exit(proc4) == 1 and "snapshot_root" in proc4.log()


def test_a_snapshot_call_sent_again_with_its_request_id_is_carried_out_once(launch, client_of, tmp_path):
    """A save or restore whose answer was lost is sent again with its request id (MemoryClient does so after
    resend_s): the node answers from the first call's answer, a refusal too, and neither saves nor restores twice."""
    storage = tmp_path / "storage"
    proc, name = start(launch, "snapresend", "-p", f"storage_dir:={storage}", "-p", "snapshot_every:=0",
                       "-p", "snapshot_service:=save_restore")
    memory = client_of(name)
    for j in range(3):
        memory.store(make_batch(4, j, 16))
    save = Snapshot.Request(op=Snapshot.Request.OP_SAVE, path="a", request_id=77)
    first = memory._call(memory._snapshot, save)
    assert not first.repeated and os.path.isdir(first.path)
    shutil.rmtree(first.path)
    again = memory._call(memory._snapshot, save)       # as if the first answer were lost
    assert again.repeated and (again.path, again.wal_sequence) == (first.path, first.wal_sequence)
    assert not os.path.exists(first.path)                # not saved a second time
    memory.snapshot("b")
    before = memory.stats()["identities"]
    memory.store(make_batch(4, 9, 16))
    restore = Snapshot.Request(op=Snapshot.Request.OP_RESTORE, path="b", request_id=78)
    assert not memory._call(memory._snapshot, restore).repeated and memory.stats()["identities"] == before
    memory.store(make_batch(4, 10, 16))
    after = memory.stats()["identities"]
    assert after > before
    assert memory._call(memory._snapshot, restore).repeated
    assert memory.stats()["identities"] == after          # the store after the restore is kept
    restore.request_id = 79                               # a new id is a new restore
    assert not memory._call(memory._snapshot, restore).repeated and memory.stats()["identities"] == before
    # a refusal is remembered too: copies of a call queued behind it are not carried out (a failed long save was
    # carried out again for each re-send); the same request with a new id is judged afresh
    late = Snapshot.Request(op=Snapshot.Request.OP_RESTORE, path="c", request_id=80)
    refused(proc, lambda: memory._call(memory._snapshot, late), "not a snapshot directory")
    memory.snapshot("c")
    again = memory._call(memory._snapshot, late, check=False)
    assert again.repeated and not again.success and "not a snapshot directory" in again.message
    late.request_id = 81
    assert not memory._call(memory._snapshot, late).repeated
    assert proc.stop() == 0


def test_repeated_sigterm_always_exits_cleanly(launch, client_of, tmp_path):
    """Issue 16 failure 6: of 50 SIGTERMs, 3 were ignored and 2 exited 1 with 'RCLError: context is
    not valid'. Eight starts (MEMORY_SIGTERM_ITERATIONS), each stopped by SIGTERM at a random
    moment under load."""
    rnd = random.Random(6)
    storage = tmp_path / "storage"
    for it in range(int(os.environ.get("MEMORY_SIGTERM_ITERATIONS", "8"))):
        proc, name = start(launch, f"term{it}", "-p", f"storage_dir:={storage}")
        memory = client_of(name)
        for j in range(rnd.randint(0, 3)):
            memory.store(make_batch(5, it * 10 + j, 16))
        memory.close()
        time.sleep(rnd.random() * 0.2)
        os.killpg(proc.proc.pid, signal.SIGTERM)
        if it % 2:
            os.killpg(proc.proc.pid, signal.SIGTERM)   # a repeated signal changes nothing
        rc = wait_exit(proc)
        log = proc.log()
        assert rc == 0 and "Traceback" not in log and "stopped (write-ahead log flushed and closed)" in log, log


def test_sigterm_while_replaying_the_log_at_start_up_exits_cleanly(launch, client_of, tmp_path):
    """A SIGTERM during construction (here: while a long WAL is replayed): rclpy's own handler shut
    the context down under the constructor, which then failed with 'RCLError: ... context is
    invalid' and exit 1. Now the node finishes starting, closes with the final flush and exits 0.
    The signal is sent 1 s after faiss is loaded into the process (its modules are imported; the
    replay takes several seconds)."""
    storage = tmp_path / "storage"
    mem = CompactMemory(MemoryConfig(storage_dir=str(storage), snapshot_every=0))
    for j in range(800):
        b = make_batch(6, j, 64)
        b.states[:, 0] = 0.0
        mem.store(b)
    mem.close()
    proc, _ = start(launch, "termreplay", "-p", f"storage_dir:={storage}")
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline and proc.alive():
        try:
            if "faiss" in Path(f"/proc/{proc.proc.pid}/maps").read_text():
                break
        except OSError:
            pass
        time.sleep(0.01)
    time.sleep(1.0)
    os.killpg(proc.proc.pid, signal.SIGTERM)
    rc = wait_exit(proc, timeout=120)
    log = proc.log()
    assert rc == 0 and "Traceback" not in log and "RCLError" not in log, log
    assert "stopped (write-ahead log flushed and closed)" in log, log


# ------------------------------------------------------------------------------------ fuzzing
def _array(draw, n):
    dtype = draw(st.sampled_from([Array.DTYPE_FLOAT32, Array.DTYPE_UINT8, 2, 255]))
    shape = draw(st.sampled_from([[n, 11], [n], [n, 11, 1], [], [n + 1, 11], [n, 0], [2**31, 2]]))
    size = int(np.prod(shape)) if shape and max(shape) < 2**20 else 3
    size += draw(st.sampled_from([0, 0, 0, 1, -1]))
    size = max(size, 0)
    vals = draw(st.sampled_from([0.0, 1.0, float("nan"), float("inf"), 1e30, -2e8]))
    a = Array(dtype=dtype if dtype < 256 else 0, shape=shape)
    if dtype == Array.DTYPE_UINT8:
        a.data_u8 = bytes([7]) * size
    else:
        a.data_f32 = [vals] * size
    return a


@st.composite
def store_requests(draw):
    n = draw(st.integers(0, 5))
    if draw(st.booleans()):
        b = transitions_to_batch(make_batch(7, draw(st.integers(0, 3)), max(n, 1)))
        field = draw(st.sampled_from(["states", "actions", "next_states", "rewards", "value_labels",
                                      "terminated", "steps", "none"]))
        if field in ("states", "actions", "next_states"):
            setattr(b, field, _array(draw, max(n, 1)))
        elif field == "rewards":
            b.rewards = [draw(st.sampled_from([0.0, float("nan"), 1e9]))] * draw(st.integers(0, 3))
        elif field == "value_labels":
            b.value_labels = [0.0] * draw(st.integers(0, 3))
        elif field == "terminated":
            b.terminated = [True] * draw(st.integers(0, 3))
        elif field == "steps":
            b.steps = [2**64 - 1] * draw(st.integers(0, 3))
    else:
        b = transitions_to_batch(make_batch(7, 0, 1))
        b.states, b.next_states, b.actions = _array(draw, n), _array(draw, n), _array(draw, n)
        b.rewards = [0.0] * n
        b.value_labels = [0.0] * draw(st.sampled_from([n, 0]))
        b.terminated = [False] * n
        b.truncated = [False] * n
    r = Store.Request()
    r.batch = b
    return ("store", r)


requests = st.one_of(
    store_requests(),
    st.builds(lambda k, s, seed, nb: ("sample", Sample.Request(batch_size=k, source=s, seed=seed, num_batches=nb)),
              st.sampled_from([0, 1, 5, 4096, 2**32 - 1]), st.integers(0, 255),
              st.sampled_from([-(2**63), -1, 0, 2**63 - 1]), st.sampled_from([0, 1, 3, 2**32 - 1])),
    st.builds(lambda k: ("begin", ReduceBegin.Request(max_sets=k)), st.sampled_from([0, 1, 7, 2**32 - 1])),
    st.builds(lambda rid, ids, preds: ("commit", ReduceCommit.Request(reduction_id=rid, identity_ids=ids,
                                                                      predictions=preds)),
              st.sampled_from([0, 1, 2, 2**64 - 1]), st.lists(st.sampled_from([0, 1, 2, 2**63, 2**64 - 1]), max_size=4),
              st.lists(st.sampled_from([0.0, float("nan"), 1e38]), max_size=4)),
    st.builds(lambda op, path: ("snapshot", Snapshot.Request(op=op, path=path)), st.integers(0, 255),
              st.one_of(st.sampled_from(["", "..", "../x", "/", "/tmp", "ok", "a/b/../../..", "//x",
                                         "ok/../../storage"]),
                        st.text(alphabet="ab./_-", max_size=12))),
)


def test_fuzzed_service_requests_are_answered_and_refusals_change_nothing(launch, client_of, tmp_path):
    proc, name = start(launch, "fuzz", "-p", f"storage_dir:={tmp_path / 'storage'}", "-p", "key_size:=26",
                       "-p", "max_store_batch:=64", "-p", "snapshot_every:=0", "-p", "lease_timeout_s:=600")
    memory = client_of(name, timeout=10.0)
    memory.store(make_batch(7, 0, 8))
    clients = {"store": memory._store, "sample": memory._sample, "begin": memory._begin,
               "commit": memory._commit, "snapshot": memory._snapshot}
    seen = {"ok": 0, "refused": 0}

    @settings(max_examples=120, deadline=None, suppress_health_check=list(HealthCheck))
    @given(req=requests)
    def check(req):
        kind, request = req
        before = memory.stats()
        try:
            memory._call(clients[kind], request, 10.0)
            seen["ok"] += 1
        except MemoryServiceError as exc:   # success=false: the reason is in the message
            seen["refused"] += 1
            assert exc.message and "internal error" not in exc.message, (kind, exc.message)
            after = memory.stats()
            assert after == before, (kind, exc.message)
        assert proc.alive(), proc.log()

    check()
    assert seen["ok"] and seen["refused"], seen
    s = memory.stats()
    assert s["identities"] >= 8
    assert proc.stop() == 0

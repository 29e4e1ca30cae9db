"""memory_node in its own process (`ros2 run comper_memory memory_node`), driven over real ROS 2
services from this test process (MemoryClient and raw requests) and from separate client
processes (memory_worker.py): store / sample / reduce / stats round trip, the two-phase reduction,
every bad input refused with a message while nothing changes, the stats topic, snapshots (and a
corrupted one refused), two concurrent learners, the rate limiter across clients, and
durability across a SIGKILL."""
from __future__ import annotations

import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from comper_memory.client import MemoryClient, MemoryServiceError, RateLimitTimeout
from comper_memory.memory_node import STATS_QOS
from comper_msgs.msg import Array, MemoryStats
from comper_msgs.srv import Sample, Store
from comper_msgs_py.arrays import Transitions
from comper_msgs_py.convert import transitions_to_batch
from memory_worker import make_batch

HERE = Path(__file__).resolve().parent
ROOT = HERE.parents[1]
MEMORY_YAML = ROOT / "src" / "comper_memory" / "config" / "memory.yaml"
WORKER = HERE / "memory_worker.py"


def start(launch, tag, *params):
    name = f"memory_{tag}_{os.getpid()}"
    proc = launch("comper_memory", "memory_node", "--ros-args", "--params-file", str(MEMORY_YAML),
                  *params, "-r", f"__node:={name}", name=name)
    return proc, name


@pytest.fixture
def client_of():
    """client_of(name) -> a standalone MemoryClient (own context, node, executor thread)."""
    made = []

    def _make(name, timeout=20.0):
        c = MemoryClient.standalone(name, timeout=timeout)
        made.append(c)
        assert c.wait_for_service(30.0), f"memory node {name} did not come up"
        return c

    yield _make
    for c in made:
        c.close()


def refused(proc, fn, *words):
    with pytest.raises(MemoryServiceError) as err:
        fn()
    for w in words:
        assert w in err.value.message, f"{w!r} not in {err.value.message!r}"
    assert proc.alive(), f"the node died on a bad request:\n{proc.log()}"
    return err.value.message


def raw_store(memory, msg_batch, timeout=10.0):
    req = Store.Request()
    req.batch = msg_batch
    return memory._call(memory._store, req, timeout)


def test_round_trip_two_phase_bad_inputs_snapshots_and_clean_stop(launch, client_of, tmp_path):
    storage = tmp_path / "storage"
    proc, name = start(launch, "main", "-p", f"storage_dir:={storage}", "-p", "key_size:=26",
                       "-p", "max_store_batch:=256", "-p", "max_sample_batch:=128",
                       "-p", "stats_period_s:=0.2", "-p", "snapshot_every:=0",
                       "-p", "snapshot_service:=save_restore")   # restores through the service (off by default)
    memory = client_of(name)
    published = []
    memory.node.create_subscription(MemoryStats, f"/{name}/stats", published.append, STATS_QOS)

    # a wrong key size before the first store (the node was told key_size 26): refused
    wrong = Transitions(np.zeros((4, 12), np.float32), np.zeros((4, 3), np.float32), np.zeros(4, np.float32),
                        np.zeros((4, 12), np.float32), np.zeros(4, bool), np.zeros(4, bool),
                        value_labels=np.zeros(4, np.float32))
    refused(proc, lambda: memory.store(wrong), "key size 28", "26")

    # --- store / re-store / stats ---
    first = make_batch(0, 0, 100)
    r = memory.store(first)
    assert r.stored == 100 and r.new_identities == 100 and r.wal_sequence == 1
    np.testing.assert_array_equal(r.identity_ids, np.arange(100, dtype=np.uint64))
    again = make_batch(0, 0, 100, label_shift=10.0)
    r2 = memory.store(again)
    assert r2.new_identities == 0 and r2.wal_sequence == 2
    np.testing.assert_array_equal(r2.identity_ids, r.identity_ids)
    s = memory.stats()
    assert (s["key_size"], s["identities"], s["tm_sets"], s["rtm_size"]) == (26, 100, 100, 0)
    assert s["transitions_stored"] == 200 and s["similarity_hits"] == 100 and s["hit_rate"] == 0.5
    assert s["wal_sequence"] == 2 and s["delta"] == pytest.approx(1e-4)

    # --- sample from TM: reproducible with a seed, newest labels, representatives as stored ---
    t, ids, counts = memory.sample(10, source="tm", seed=5)
    t2, ids2, _ = memory.sample(10, source="tm", seed=5)
    np.testing.assert_array_equal(ids, ids2)
    np.testing.assert_array_equal(t.states, t2.states)
    assert len(set(ids.tolist())) == 10 and (counts == 2).all()
    idx = ids.astype(np.int64)
    np.testing.assert_array_equal(t.states, first.states[idx])
    np.testing.assert_array_equal(t.actions, first.actions[idx])
    np.testing.assert_array_equal(t.terminated, first.terminated[idx])
    np.testing.assert_array_equal(t.value_labels, again.value_labels[idx])
    refused(proc, lambda: memory.sample(10), "exceeds the 0 entries of RTM")

    # --- one-call reduction (newest label = prediction) ---
    red = memory.reduce(max_sets=40)
    assert red.sets_reduced == 40 and red.rtm_size == 40

    # --- two-phase reduction, as a QT trainer drives it ---
    lease = memory.reduce_begin(max_sets=30)
    assert len(lease) == 30 and lease.reduction_id > 0
    np.testing.assert_array_equal(lease.identity_ids, np.arange(40, 70, dtype=np.uint64))  # oldest first
    assert (lease.history_lengths == 2).all() and (lease.counts == 2).all()
    hist = np.stack(lease.histories())
    np.testing.assert_array_equal(hist[:, 0], first.value_labels[40:70])
    np.testing.assert_array_equal(hist[:, 1], again.value_labels[40:70])
    np.testing.assert_array_equal(lease.representatives.states, first.states[40:70])
    assert memory.stats()["tm_sets"] == 30
    refused(proc, lambda: memory.reduce_commit(lease.reduction_id, lease.identity_ids[::-1][:29], np.zeros(29)),
            "differ")
    preds = np.linspace(-1, 1, 30).astype(np.float32)
    bad = preds.copy()
    bad[3] = np.nan
    refused(proc, lambda: memory.reduce_commit(lease.reduction_id, lease.identity_ids, bad), "NaN")
    c = memory.reduce_commit(lease.reduction_id, lease.identity_ids, preds)
    assert c.committed == 30 and c.rtm_size == 70
    refused(proc, lambda: memory.reduce_commit(lease.reduction_id, lease.identity_ids, preds), "unknown")
    refused(proc, lambda: memory.reduce_commit(999, [1, 2], [0.0, 0.0]), "reduction 999 is unknown")

    t, ids, _ = memory.sample(70, seed=1)
    got = dict(zip(ids.tolist(), t.value_labels.tolist()))
    for i, p in zip(range(40, 70), preds):
        assert got[i] == pytest.approx(float(p))
    for i in range(40):
        assert got[i] == pytest.approx(float(again.value_labels[i]))
    s = memory.stats()
    assert (s["rtm_size"], s["tm_sets"], s["reductions"], s["sets_reduced"]) == (70, 30, 2, 70)

    # --- every bad input: success=false, a clear message, nothing changed, node still serves ---
    before = memory.stats()
    nan = make_batch(0, 1, 8)
    nan.states[5, 2] = np.nan
    refused(proc, lambda: memory.store(nan), "NaN or Inf")
    inf = make_batch(0, 1, 8)
    inf.value_labels[2] = np.inf
    refused(proc, lambda: memory.store(inf), "NaN or Inf")
    obs12 = make_batch(0, 1, 8)
    obs12.states = np.zeros((8, 12), np.float32)
    obs12.next_states = np.zeros((8, 12), np.float32)
    refused(proc, lambda: memory.store(obs12), "differ")
    refused(proc, lambda: memory.store(make_batch(0, 1, 8).take(slice(0, 0))), "empty batch")
    refused(proc, lambda: memory.store(make_batch(0, 1, 300)), "300", "max_store_batch (256)")
    nolabels = make_batch(0, 1, 8)
    nolabels.value_labels = np.zeros(0, np.float32)
    refused(proc, lambda: memory.store(nolabels), "value_labels")
    malformed = transitions_to_batch(make_batch(0, 1, 8))
    malformed.states = Array(dtype=Array.DTYPE_FLOAT32, shape=[8, 11], data_f32=[0.0] * 10)
    refused(proc, lambda: raw_store(memory, malformed), "needs 88 values")
    refused(proc, lambda: memory.sample(129), "max_sample_batch=128")
    refused(proc, lambda: memory._call(memory._sample, Sample.Request(batch_size=4, source=7, seed=-1), 10.0),
            "unknown source 7")
    with pytest.raises(ValueError, match="source"):
        memory.sample(4, source="xyz")
    assert memory.stats() == before, "a refused request changed the memory"
    # the stats topic carries the same gauge (best effort, keep last 1)
    def current(m):  # a message published after the last change (earlier ones may still arrive first)
        return (m.identities, m.rtm_size, m.tm_sets, m.transitions_stored, m.reductions) == \
            (100, 70, 30, before["transitions_stored"], 2)
    deadline = time.monotonic() + 10
    while not (published and current(published[-1])) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert published, "nothing on ~/stats"
    assert current(published[-1]) and published[-1].key_size == 26, published[-1]
    ok = memory.store(make_batch(0, 1, 8))
    assert ok.new_identities == 8

    # --- snapshots through the service ---
    snap = storage / "snapshots" / "snap1"  # named snapshots live under snapshot_root
    path, seq = memory.snapshot("snap1")
    assert path == str(snap) and (snap / "manifest.json").exists()
    saved = memory.stats()
    memory.store(make_batch(0, 2, 50))
    assert memory.stats()["identities"] == 158
    path, _ = memory.restore(str(snap))  # an absolute path inside snapshot_root
    restored = memory.stats()
    for k in ("identities", "tm_sets", "rtm_size", "transitions_stored", "reductions", "sets_reduced"):
        assert restored[k] == saved[k], k
    t, ids, _ = memory.sample(70, seed=1)
    assert len(ids) == 70
    restored = memory.stats()     # (the sample moved the rate limiter's counts)
    # a corrupted copy is refused with a clear message and changes nothing
    bad_snap = storage / "snapshots" / "bad"
    shutil.copytree(snap, bad_snap)
    raw = bytearray((bad_snap / "state.npz").read_bytes())
    raw[len(raw) // 2] ^= 0xFF
    (bad_snap / "state.npz").write_bytes(bytes(raw))
    refused(proc, lambda: memory.restore(str(bad_snap)), "checksum mismatch")
    refused(proc, lambda: memory.restore("nowhere"), "not a snapshot directory")
    refused(proc, lambda: memory.restore(str(tmp_path / "elsewhere")), "outside snapshot_root")
    assert memory.stats() == restored
    # '' = the node's storage directory (snapshot + WAL rotation)
    path, seq = memory.snapshot("")
    assert path == str(storage / "snapshot") and (storage / "snapshot" / "manifest.json").exists()

    # --- Ctrl-C: clean exit 0, one start line, final flush, warnings rate-limited ---
    assert proc.stop() == 0
    log = proc.log_path.read_text(errors="replace")
    assert "Traceback" not in log, log
    assert log.count("serving: delta") == 1 and "storage " + str(storage) in log
    assert "stopped (write-ahead log flushed and closed)" in log
    # 15 refused requests within a few seconds: at most one warning line per second
    warnings = [ln for ln in log.splitlines() if "refused" in ln and "WARN" in ln]
    assert 1 <= len(warnings) < 15, warnings


def test_two_learner_processes_store_and_sample_concurrently(launch, client_of, tmp_path):
    # the multi-threaded executor (the other tests run the default single-threaded one)
    proc, name = start(launch, "concurrent", "-p", "stats_period_s:=0.5", "-p", "executor_threads:=4")
    memory = client_of(name)
    n_batches, batch = 25, 32
    workers = []
    for w in (1, 2):
        out = tmp_path / f"worker{w}.json"
        log = open(tmp_path / f"worker{w}.log", "wb")
        workers.append((out, log, subprocess.Popen(
            [sys.executable, str(WORKER), "--node", name, "--worker", str(w), "--batches", str(n_batches),
             "--batch", str(batch), "--out", str(out)], stdout=log, stderr=subprocess.STDOUT,
            env=os.environ.copy())))
    for out, log, p in workers:
        try:
            rc = p.wait(timeout=90)
        finally:
            if p.poll() is None:
                p.kill()
            log.close()
        assert rc == 0, (tmp_path / f"{out.stem}.log").read_text()
    results = [json.loads(out.read_text()) for out, _, _ in workers]
    total = 2 * n_batches * batch
    all_ids = [i for r in results for i in r["identity_ids"]]
    assert len(all_ids) == total and len(set(all_ids)) == total, "identities lost or shared"
    assert all(r["samples"] > 0 for r in results)
    s = memory.stats()
    assert s["identities"] == total and s["transitions_stored"] == total and s["similarity_hits"] == 0
    assert s["tm_sets"] + s["rtm_size"] >= total  # reduced sets sit in RTM, the rest in TM
    # re-storing everything creates nothing new and maps every transition to its identity
    for w, r in zip((1, 2), results):
        ids = []
        for j in range(n_batches):
            reply = memory.store(make_batch(w, j, batch))
            assert reply.new_identities == 0
            ids.extend(reply.identity_ids.tolist())
        assert ids == r["identity_ids"]
    s2 = memory.stats()
    assert s2["identities"] == total and s2["transitions_stored"] == 2 * total
    assert proc.alive()


def _in_thread(fn):
    import threading
    out = {}

    def run():
        try:
            out["value"] = fn()
        except Exception as exc:     # reported by the test
            out["error"] = exc
    t = threading.Thread(target=run, daemon=True)
    t.start()
    return t, out


def test_rate_limiter_holds_every_client_to_the_ratio(launch, client_of):
    """samples_per_insert 1, error buffer 64, min size 32: a sampler waits for another client's
    stores, a storer for another client's samples, a wait past rate_limit_timeout ends in
    RateLimitTimeout, a call that could never pass is refused at once; the node serves the other
    clients meanwhile and its stats report the ratio held."""
    proc, name = start(launch, "rate", "-p", "samples_per_insert:=1.0", "-p", "rate_error_buffer:=64.0",
                       "-p", "min_size_to_sample:=32")
    sampler, storer, watcher = client_of(name), client_of(name), client_of(name)
    t, out = _in_thread(lambda: sampler.sample(8, "tm"))          # nothing stored yet: waits
    time.sleep(1.0)
    assert t.is_alive() and watcher.stats()["rate_limited_samples"] >= 1   # the node answers others
    storer.store(make_batch(1, 0, 64))
    t.join(20)
    assert not t.is_alive() and "error" not in out and len(out["value"][0]) == 8
    assert sampler.rate_limited_waits == 1
    storer.store(make_batch(1, 1, 32))                            # 96 - 8 = 88 owed: a store of 16 waits
    t, out = _in_thread(lambda: storer.store(make_batch(1, 2, 16)))
    time.sleep(1.0)
    assert t.is_alive() and watcher.stats()["transitions_stored"] == 96
    sampler.sample(32, "tm")                                       # 56 owed: the store passes
    t.join(20)
    assert not t.is_alive() and "error" not in out and out["value"].stored == 16
    quick = MemoryClient.standalone(name, timeout=20.0, rate_limit_timeout=0.5)
    try:
        assert quick.wait_for_service(30.0)
        quick.sample(32, "tm", num_batches=2)                      # 72 - 64 = 8 owed: inside [-32, 96]
        t0 = time.monotonic()
        with pytest.raises(RateLimitTimeout, match="waits for stores"):
            quick.sample(48, "tm")                                 # 8 - 48 = -40: below the band
        assert 0.4 < time.monotonic() - t0 < 5.0
    finally:
        quick.close()
    refused(proc, lambda: storer.store(make_batch(1, 3, 200)), "could never pass")
    s = watcher.stats()
    assert (s["rate_inserts"], s["rate_samples"]) == (112, 104)
    assert s["samples_per_insert_held"] == pytest.approx(104 / 112)
    assert s["rate_limited_stores"] >= 1 and s["rate_limited_samples"] >= 3
    assert proc.alive()


def test_acknowledged_stores_survive_sigkill(launch, client_of, tmp_path):
    storage = tmp_path / "storage"
    params = ("-p", f"storage_dir:={storage}", "-p", "durability:=flush", "-p", "snapshot_every:=7")
    proc, name = start(launch, "durable", *params)
    client_of(name)  # waits until the services are up
    acks = tmp_path / "acks.txt"
    batch = 16
    log = open(tmp_path / "writer.log", "wb")
    writer = subprocess.Popen([sys.executable, str(WORKER), "--node", name, "--worker", "3", "--batch", str(batch),
                               "--ack-file", str(acks), "--continuous"],
                              stdout=log, stderr=subprocess.STDOUT, env=os.environ.copy())
    try:
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline and (not acks.exists() or len(acks.read_text().split()) < 25):
            assert writer.poll() is None, (tmp_path / "writer.log").read_text()
            time.sleep(0.05)
        proc.kill(signal.SIGKILL)  # mid-load: the writer is storing continuously
        assert writer.wait(timeout=30) == 0
    finally:
        if writer.poll() is None:
            writer.kill()
        log.close()
    acked = [int(x) for x in acks.read_text().split()]
    assert len(acked) >= 25 and acked == list(range(len(acked)))
    assert "stopped after" in (tmp_path / "writer.log").read_text()

    proc2, name2 = start(launch, "durable2", *params)
    memory = client_of(name2)
    s = memory.stats()
    assert s["identities"] >= len(acked) * batch and s["transitions_stored"] >= len(acked) * batch
    assert s["wal_sequence"] >= len(acked)
    for j in acked:  # every acknowledged transition is back: re-storing creates nothing new
        assert memory.store(make_batch(3, j, batch)).new_identities == 0
    assert memory.stats()["identities"] == s["identities"]
    assert re.search(r"recovered \d+ identities", proc2.log())

    # SIGTERM: clean exit 0 with the final flush
    proc2.kill(signal.SIGTERM)
    assert proc2.proc.returncode == 0, proc2.log()
    assert "stopped (write-ahead log flushed and closed)" in proc2.log()


def test_bad_parameter_is_refused_at_start(launch):
    proc, _ = start(launch, "badparam", "-p", "durability:=sometimes")
    assert proc.proc.wait(timeout=30) == 1
    log = proc.log()
    assert "cannot start" in log and "durability" in log and "Traceback" not in log


def test_key_normalisation_through_the_node(launch, client_of):
    """`-p key_normalisation:=running`: the first reduction freezes the keys' mean and scale and the node's
    stats say so; an unknown mode stops the node at start with the parameter named."""
    proc, name = start(launch, "keynorm", "-p", "key_normalisation:=running", "-p", "delta:=0.5")
    memory = client_of(name)
    memory.store(make_batch(2, 0, 200))
    s = memory.stats()
    assert (s["key_norm_updates"], s["key_norm_keys"]) == (0, 0)
    memory.reduce(max_sets=50)
    s = memory.stats()
    assert (s["key_norm_updates"], s["key_norm_keys"]) == (1, 200) and s["identities"] == 200
    # the same transitions again: distance 0 under the new map, so they join their identities
    r = memory.store(make_batch(2, 0, 200, label_shift=1.0))
    assert r.new_identities == 0
    assert proc.alive()
    bad, _ = start(launch, "keynormbad", "-p", "key_normalisation:=zscore")
    assert bad.proc.wait(timeout=30) == 1
    assert "key_normalisation" in bad.log() and "Traceback" not in bad.log()

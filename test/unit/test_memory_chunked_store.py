"""Large stores applied in chunks (issue 16, core level): the chunked path gives the same memory as one
store of the whole batch, other calls run between chunks, a refused batch stores nothing, the log
replays exactly what was applied (also after a kill between chunks), and a restore waits for a
store in progress."""
from __future__ import annotations

import glob
import os
import shutil

import numpy as np
import pytest

from comper_memory.core import CompactMemory, MemoryConfig, MemoryInputError, RateLimited
from comper_msgs_py.arrays import Transitions
from test_memory_hardening import assert_same, make, state_of


def without_sequence(state):
    """state_of(mem) minus the log sequence (one record per chunk instead of one per store)."""
    arrays, meta, stats = state
    stats = {k: v for k, v in stats.items() if k != "wal_sequence"}
    meta = {**meta, "counters": {k: v for k, v in meta["counters"].items() if k != "wal_sequence"}}
    return arrays, meta, stats


def big_batch(seed=0, n=3000, restores=1000):
    """n new transitions plus `restores` exact repeats of earlier ones of the same batch."""
    rng = np.random.default_rng(seed)
    base = make(rng, n)
    return Transitions.concatenate([base, base.take(rng.integers(0, n, restores))])


def run_chunks(mem, t, chunk, between=lambda i: None):
    op = mem.begin_store(t, chunk)
    i = 0
    while not op.done:
        between(i)
        op.step()
        i += 1
    return op


def test_chunked_store_gives_the_same_memory_as_one_store():
    pre = make(np.random.default_rng(1), 500)
    t = big_batch()
    one, chunked = CompactMemory(MemoryConfig()), CompactMemory(MemoryConfig())
    one.store(pre)
    chunked.store(pre)
    whole = one.store(t)
    op = run_chunks(chunked, t, 512)
    assert op.chunks == 8 and op.applied == len(t)
    r = op.result()
    np.testing.assert_array_equal(r.identity_ids, whole.identity_ids)
    assert (r.new_identities, r.similarity_hits, r.evicted) == (whole.new_identities, whole.similarity_hits, 0)
    assert (one.wal_sequence, chunked.wal_sequence) == (2, 9)   # one record per chunk
    assert_same(without_sequence(state_of(one)), without_sequence(state_of(chunked)))


def test_other_calls_run_between_chunks_and_see_the_chunks_applied_so_far():
    t = big_batch(n=2000, restores=0)
    mem = CompactMemory(MemoryConfig())
    seen = []

    def between(i):   # what another client does while the store is in progress
        s = mem.stats()
        seen.append(s["transitions_stored"])
        mem.sample(8, source="tm", seed=i)
        if i == 1:
            mem.store(make(np.random.default_rng(7), 10))   # another client's small store
    op = run_chunks(mem, t, 500, between)
    assert seen == [500, 1000, 1510]           # after chunk 1, 2 (+ the small store), 3
    r = op.result()
    # the small store took the ids after the first two chunks' identities: it was applied between them
    np.testing.assert_array_equal(r.identity_ids[:1000], np.arange(1000))
    np.testing.assert_array_equal(r.identity_ids[1000:], np.arange(1010, 2010))
    assert mem.stats()["transitions_stored"] == 2010


def test_a_refused_large_batch_stores_nothing():
    mem = CompactMemory(MemoryConfig())
    mem.store(make(np.random.default_rng(1), 10))
    before = state_of(mem)
    t = big_batch(n=2000, restores=0)
    t.states[-1, 0] = np.nan            # bad input in the last chunk
    with pytest.raises(MemoryInputError, match="NaN"):
        mem.begin_store(t, 256)
    assert_same(state_of(mem), before)


def test_rate_limiter_admits_or_holds_the_whole_batch():
    mem = CompactMemory(MemoryConfig(samples_per_insert=1.0, rate_error_buffer=1500.0, min_size_to_sample=10))
    mem.store(make(np.random.default_rng(1), 10))
    op = mem.begin_store(big_batch(n=1400, restores=0), 200)   # admitted whole ...
    assert mem.rate.inserts == 1410
    with pytest.raises(RateLimited):                           # ... so the next store waits for samples
        mem.store(make(np.random.default_rng(2), 200))
    op.result()
    assert mem.stats()["transitions_stored"] == 1410


def killed_mid_store(tmp_path, request_id=0):
    """A persistent memory with 50 transitions, then a 2,000-transition store in chunks of 250 with other
    clients' stores and reductions between its chunks; after 4 chunks, a kill: a copy of the storage as it
    is on disk (flush durability: every record is written). (cfg, mem, op, batch, killed_dir); the live
    memory and its store go on."""
    live_dir, killed_dir = tmp_path / "live", tmp_path / "killed"
    cfg = MemoryConfig(storage_dir=str(live_dir), snapshot_every=3)   # checkpoints between chunks too
    mem = CompactMemory(cfg)
    mem.store(make(np.random.default_rng(1), 50))
    t = big_batch(n=1800, restores=200)
    op = mem.begin_store(t, 250, request_id=request_id)
    for i in range(3):
        op.step()
        mem.store(make(np.random.default_rng(10 + i), 5))       # other clients between chunks
        mem.reduce(max_sets=100)
    shutil.copytree(live_dir, killed_dir)
    return cfg, mem, op, t, killed_dir


def test_log_replays_interleaved_chunks_and_a_kill_between_chunks_leaves_a_startable_state(tmp_path):
    cfg, mem, op, t, killed_dir = killed_mid_store(tmp_path)
    partial = without_sequence(state_of(mem))
    op.result()
    live = state_of(mem)
    mem.close()

    again = CompactMemory(cfg)           # the log replays the chunks and the calls between them in order
    assert_same(state_of(again), live)
    again.close()
    killed = CompactMemory(MemoryConfig(storage_dir=str(killed_dir), snapshot_every=3))
    assert not glob.glob(os.path.join(killed_dir, "*.tmp-*"))
    assert_same(without_sequence(state_of(killed)), partial)   # exactly the first 4 chunks + the rest
    assert killed.stats()["transitions_stored"] == 50 + 4 * 250 + 3 * 5
    # the client re-sends the unanswered batch: the stored part joins its identities, nothing is lost
    r = killed.store(t)
    assert r.new_identities == 1800 - 4 * 250
    assert killed.stats()["identities"] == live[2]["identities"]
    killed.close()


def test_restore_waits_for_a_store_in_progress_and_a_closed_memory_applies_nothing(tmp_path):
    mem = CompactMemory(MemoryConfig(storage_dir=str(tmp_path / "s"), snapshot_every=0))
    mem.store(make(np.random.default_rng(1), 20))
    mem.save_snapshot(str(tmp_path / "named"))
    op = mem.begin_store(big_batch(n=1000, restores=0), 300)
    with pytest.raises(MemoryInputError, match="in chunks"):
        mem.load_snapshot(str(tmp_path / "named"))
    op.result()
    mem.load_snapshot(str(tmp_path / "named"))            # once it is done
    assert mem.stats()["identities"] == 20
    op = mem.begin_store(big_batch(seed=3, n=1000, restores=0), 300)
    mem.close()
    with pytest.raises(MemoryInputError, match="300 of 1000"):
        op.step()
    assert op.applied == 300


def test_a_resent_store_is_answered_from_the_first_and_never_applied_twice():
    mem = CompactMemory(MemoryConfig(resend_window=150))
    t = make(np.random.default_rng(1), 60)
    first = mem.store(t, request_id=7)
    again = mem.begin_store(t, request_id=7)            # its answer was lost; the client sends it again
    assert again.repeated and again.done
    np.testing.assert_array_equal(again.result().identity_ids, first.identity_ids)
    assert mem.stats()["transitions_stored"] == 60

    big = big_batch(n=1000, restores=0)                 # a re-send while the first is still being applied
    op = mem.begin_store(big, 256, request_id=8)
    resent = mem.begin_store(big, 256, request_id=8)
    assert resent.repeated and not resent.done
    while not resent.done:
        resent.step()                                   # either one's steps apply the same chunks
    assert op.done and mem.stats()["transitions_stored"] == 1060
    assert op._t is None and op._keys is None          # what is remembered is the answer, not the batch
    np.testing.assert_array_equal(resent.result().identity_ids, op.result().identity_ids)

    mem.store(make(np.random.default_rng(2), 60), request_id=9)   # 60 + 1000 + 60 > 150: 7 and 8 forgotten
    assert not mem.begin_store(t, request_id=7).repeated           # applied again: joins its identities
    assert mem.stats()["transitions_stored"] == 1180 and mem.stats()["identities"] == 1120
    assert mem.begin_store(make(np.random.default_rng(2), 60), request_id=9).repeated
    assert not mem.begin_store(t).repeated                          # no id: always applied


def test_a_resent_store_is_not_held_back_by_the_rate_limiter():
    mem = CompactMemory(MemoryConfig(samples_per_insert=1.0, rate_error_buffer=100.0, min_size_to_sample=10))
    mem.store(make(np.random.default_rng(1), 10))
    t = make(np.random.default_rng(2), 100)
    mem.store(t, request_id=5)                          # the balance is now at its limit
    with pytest.raises(RateLimited):
        mem.store(make(np.random.default_rng(3), 10))
    assert mem.begin_store(t, request_id=5).repeated    # the re-send is answered, not held back


def test_remembered_answers_survive_a_restart_through_the_log_and_the_snapshot(tmp_path):
    for every in (0, 2):   # 0: the WAL alone; 2: checkpoints between the stores, the snapshot holds them
        cfg = MemoryConfig(storage_dir=str(tmp_path / f"s{every}"), snapshot_every=every, resend_window=10_000)
        mem = CompactMemory(cfg)
        t = make(np.random.default_rng(1), 60)
        first = mem.store(t, request_id=11)
        big = big_batch(n=700, restores=100)
        op = mem.begin_store(big, 256, request_id=12)
        mem.store(make(np.random.default_rng(2), 5), request_id=13)    # another client between chunks
        mem.reduce(max_sets=20)
        whole = op.result()
        live = state_of(mem)
        mem.close()

        again = CompactMemory(cfg)
        assert_same(state_of(again), live)                             # the answers are part of the state
        for rid, batch, answer in ((11, t, first), (12, big, whole)):
            resent = again.begin_store(batch, 256, request_id=rid)
            assert resent.repeated and resent.done
            np.testing.assert_array_equal(resent.result().identity_ids, answer.identity_ids)
        assert again.stats()["transitions_stored"] == live[2]["transitions_stored"]
        again.close()


def test_a_batch_cut_short_by_a_kill_is_completed_once_by_its_resend(tmp_path):
    cfg, mem, op, t, killed_dir = killed_mid_store(tmp_path, request_id=21)   # a kill after 4 of the 8 chunks
    whole = op.result()
    live = state_of(mem)
    mem.close()

    killed = CompactMemory(MemoryConfig(storage_dir=str(killed_dir), snapshot_every=3))
    assert killed.stats()["transitions_stored"] == 50 + 4 * 250 + 3 * 5
    with pytest.raises(MemoryInputError, match="request id 21 was a batch of 2000 transitions, 1000 of them"):
        killed.begin_store(t.take(slice(0, 1999)), 250, request_id=21)
    assert killed.stats()["transitions_stored"] == 50 + 4 * 250 + 3 * 5
    resent = killed.begin_store(t, 250, request_id=21)   # the client re-sends the unanswered batch
    assert resent.repeated
    r = resent.result()
    # the chunks left are applied from the re-send, the stored ones not again: the memory the kill interrupted
    np.testing.assert_array_equal(r.identity_ids, whole.identity_ids)
    assert (r.new_identities, r.similarity_hits) == (whole.new_identities, whole.similarity_hits)
    assert_same(state_of(killed), live)
    assert killed.begin_store(t, request_id=21).repeated
    killed.close()


def test_a_batch_cut_short_and_never_resent_is_forgotten_like_an_old_answer(tmp_path):
    _, mem, _, t, killed_dir = killed_mid_store(tmp_path, request_id=21)
    mem.close()
    killed = CompactMemory(MemoryConfig(storage_dir=str(killed_dir), snapshot_every=3, resend_window=100))
    stored = killed.stats()["transitions_stored"]
    assert killed.stores.known(21).needs_batch
    killed.store(make(np.random.default_rng(5), 60), request_id=50)   # 60 newer answers: still waiting
    assert killed.stores.known(21) is not None
    killed.store(make(np.random.default_rng(6), 60), request_id=51)   # 120 > resend_window: forgotten
    assert killed.stores.known(21) is None
    assert 21 not in killed.stores.arrays()["resend_requests"][:, 0]   # nor kept by the next snapshot
    late = killed.begin_store(t, 250, request_id=21)                  # a re-send now is a new store
    assert not late.repeated
    late.result()
    assert killed.stats()["transitions_stored"] == stored + 120 + 2000
    killed.close()


def test_a_restored_snapshot_brings_its_own_answers(tmp_path):
    mem = CompactMemory(MemoryConfig(storage_dir=str(tmp_path / "s"), snapshot_every=0))
    before, after = make(np.random.default_rng(1), 30), make(np.random.default_rng(2), 30)
    mem.store(before, request_id=31)
    mem.save_snapshot(str(tmp_path / "named"))
    mem.store(after, request_id=32)
    mem.load_snapshot(str(tmp_path / "named"))
    assert mem.begin_store(before, request_id=31).repeated       # in the restored state: answered
    assert not mem.begin_store(after, request_id=32).repeated    # not in it: applied
    assert mem.stats()["transitions_stored"] == 60
    mem.close()


def test_a_snapshot_with_a_damaged_answer_table_is_refused(tmp_path):
    from comper_memory.core import storage as st
    mem = CompactMemory(MemoryConfig())
    mem.store(make(np.random.default_rng(1), 30), request_id=41)
    mem.save_snapshot(str(tmp_path / "good"))
    arrays, meta = st.read_snapshot(str(tmp_path / "good"))
    assert arrays["resend_requests"].tolist() == [[41, 30, 30, 30, 0, 0, 1]]   # id, n, applied, new, hits, evicted, sequence
    arrays["resend_requests"][0, 2] = 29                          # applied no longer matches the ids
    st.write_snapshot(str(tmp_path / "bad"), arrays, meta)
    other = CompactMemory(MemoryConfig())
    with pytest.raises(st.SnapshotError, match="resend arrays"):
        other.load_snapshot(str(tmp_path / "bad"))
    assert other.stats()["identities"] == 0

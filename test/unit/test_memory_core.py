"""TM / RTM / reduction / sampling / capacity / input validation of CompactMemory."""
import threading

import numpy as np
import pytest

from comper_memory.core import (CompactMemory, LeaseError, MemoryConfig, MemoryInputError,
                                transition_keys)
from comper_msgs_py.arrays import Transitions
from comper_msgs_py.params import ConfigError


def make(rng, n, obs=4):
    return Transitions(rng.standard_normal((n, obs)).astype(np.float32),
                       rng.standard_normal((n, 1)).astype(np.float32),
                       rng.standard_normal(n).astype(np.float32),
                       rng.standard_normal((n, obs)).astype(np.float32),
                       np.zeros(n, bool), np.zeros(n, bool),
                       value_labels=rng.standard_normal(n).astype(np.float32),
                       steps=np.arange(n, dtype=np.uint64))


def relabel(t, labels):
    return Transitions(t.states, t.actions, t.rewards, t.next_states, t.terminated, t.truncated,
                       value_labels=np.asarray(labels, np.float32), steps=t.steps)


class Clock:
    def __init__(self):
        self.t = 0.0

    def __call__(self):
        return self.t


def test_key_layout():
    rng = np.random.default_rng(0)
    t = Transitions(rng.integers(0, 256, (2, 84, 84), dtype=np.uint8), np.array([3, 7]),
                    np.array([1.0, -1.0], np.float32), rng.integers(0, 256, (2, 84, 84), dtype=np.uint8),
                    np.zeros(2, bool), np.zeros(2, bool))
    k = transition_keys(t)
    assert k.shape == (2, 14114) and k.dtype == np.float32
    np.testing.assert_array_equal(k[:, :7056], t.states.reshape(2, -1).astype(np.float32) * np.float32(1 / 255))
    np.testing.assert_array_equal(k[:, 7056], [3, 7])
    np.testing.assert_array_equal(k[:, 7057], [1, -1])
    assert k[:, :7056].max() <= 1.0 and k[:, 7058:].max() <= 1.0
    # written in place: the same bits as the cast, scaled copy and concatenation it replaces, also into `out`
    np.testing.assert_array_equal(k[:, 7058:], t.next_states.reshape(2, -1).astype(np.float32) * np.float32(1 / 255))
    out = np.full((2, 14114), np.nan, np.float32)
    assert transition_keys(t, out=out) is out and np.array_equal(out, k)
    with pytest.raises(ValueError, match="out must be"):
        transition_keys(t, out=np.empty((2, 14114), np.float64))
    f = make(rng, 3, obs=5)
    f = Transitions(f.states.astype(np.float64), f.actions, f.rewards, f.next_states, f.terminated, f.truncated)
    np.testing.assert_array_equal(transition_keys(f), np.concatenate(
        [f.states.astype(np.float32), f.actions, f.rewards[:, None], f.next_states], axis=1))


def test_tm_rtm_reduce_and_sample():
    rng = np.random.default_rng(1)
    mem = CompactMemory(MemoryConfig(delta=0.0, history_length=3))
    t = make(rng, 10)
    r = mem.store(t)
    assert r.new_identities == 10 and mem.tm_size == 10 and mem.rtm_size == 0
    for lab in (1.0, 2.0, 3.0, 4.0):  # re-store ids 0..2 with fresh labels: history keeps newest 3
        mem.store(relabel(t.take(np.arange(3)), [lab] * 3))
    lease = mem.begin_reduce(4)
    np.testing.assert_array_equal(lease.identity_ids, [0, 1, 2, 3])  # oldest first
    np.testing.assert_array_equal(lease.history_lengths, [3, 3, 3, 1])
    np.testing.assert_array_equal(lease.histories()[0], [2, 3, 4])
    np.testing.assert_array_equal(lease.counts, [5, 5, 5, 1])
    np.testing.assert_array_equal(lease.representatives.value_labels[:3], [4, 4, 4])
    np.testing.assert_array_equal(lease.representatives.states, t.states[:4])
    assert mem.tm_size == 6
    mem.commit_reduce(lease.reduction_id, lease.identity_ids, np.array([10, 11, 12, 13], np.float32))
    assert mem.rtm_size == 4
    s = mem.sample(4, seed=0)
    assert sorted(s.identity_ids.tolist()) == [0, 1, 2, 3]
    np.testing.assert_array_equal(s.transitions.value_labels, 10 + s.identity_ids)
    with pytest.raises(MemoryInputError):
        mem.sample(5)
    assert len(mem.sample(5, allow_fewer=True).identity_ids) == 4
    s = mem.sample(6, source="tm", seed=1)
    assert len(set(s.identity_ids.tolist())) == 6 and set(s.identity_ids.tolist()) == set(range(4, 10))
    # reduce() with the built-in predictor drains TM oldest first
    mem.reduce()
    assert mem.tm_size == 0 and mem.rtm_size == 10
    st = mem.stats()
    assert st["compaction_ratio"] == 10 / 22 and st["reductions"] == 2 and st["sets_reduced"] == 10
    with pytest.raises(LeaseError):
        mem.commit_reduce(lease.reduction_id, lease.identity_ids, np.zeros(4, np.float32))


def test_sample_uniform_distinct():
    rng = np.random.default_rng(2)
    mem = CompactMemory(MemoryConfig())
    mem.store(make(rng, 50))
    mem.reduce()
    hits = np.zeros(50)
    g = np.random.default_rng(0)
    for _ in range(400):
        ids = mem.sample(10, rng=g).identity_ids
        assert len(np.unique(ids)) == 10
        hits[ids] += 1
    assert hits.min() > 40 and hits.max() < 120  # expectation 80


def test_sample_num_batches_are_independent_distinct_draws():
    rng = np.random.default_rng(4)
    mem = CompactMemory(MemoryConfig(max_sample_batch=100))
    mem.store(make(rng, 30))
    mem.reduce()
    res = mem.sample(20, rng=np.random.default_rng(1), num_batches=5)
    assert len(res.transitions) == 100 and res.identity_ids.shape == (100,)
    blocks = res.identity_ids.reshape(5, 20)
    assert all(len(np.unique(b)) == 20 for b in blocks)        # distinct within each batch
    assert len({tuple(sorted(b)) for b in blocks}) > 1          # independent draws, not one repeated
    # the same rows as five one-batch draws from the same generator
    g = np.random.default_rng(1)
    one_by_one = np.concatenate([mem.sample(20, rng=g).identity_ids for _ in range(5)])
    np.testing.assert_array_equal(res.identity_ids, one_by_one)
    with pytest.raises(MemoryInputError, match="max_sample_batch"):
        mem.sample(20, num_batches=6)                           # 120 rows > 100: refused


def test_store_into_leased_set_is_not_lost_and_expiry_returns_to_front():
    rng = np.random.default_rng(3)
    clock = Clock()
    mem = CompactMemory(MemoryConfig(delta=0.0, lease_timeout_s=5.0), clock=clock)
    t = make(rng, 6)
    mem.store(t)
    lease = mem.begin_reduce(3)
    mem.store(relabel(t.take(np.array([1])), [42.0]))  # stored into a leased set
    assert mem.tm_size == 4
    mem.commit_reduce(lease.reduction_id, lease.identity_ids, np.zeros(3, np.float32))
    assert mem.rtm_size == 3 and mem.tm_size == 4
    nxt = mem.begin_reduce(10)
    assert 1 in nxt.identity_ids.tolist()
    k = nxt.identity_ids.tolist().index(1)
    assert nxt.representatives.value_labels[k] == 42.0 and nxt.counts[k] == 2
    # expiry: the lease's sets go back to the front of TM, committing then fails
    mem.store(make(rng, 2))
    clock.t = 10.0
    assert mem.tm_size == 6
    lease2 = mem.begin_reduce(4)
    np.testing.assert_array_equal(lease2.identity_ids, nxt.identity_ids[:4])
    with pytest.raises(LeaseError):
        mem.commit_reduce(nxt.reduction_id, nxt.identity_ids, np.zeros(len(nxt), np.float32))


def test_capacity_eviction_consistent():
    rng = np.random.default_rng(4)
    mem = CompactMemory(MemoryConfig(delta=0.0, rtm_capacity=20, tm_capacity=20, max_store_batch=10))
    first = make(rng, 10)
    mem.store(first)
    mem.reduce()
    mem.store(make(rng, 10))
    mem.store(relabel(first.take(np.arange(5)), np.ones(5)))  # ids 0..4 are now recently updated
    r = mem.store(make(rng, 10))
    assert r.evicted == 10
    live = set(mem.slots.ids_sorted.tolist())
    assert len(live) == 20
    assert {5, 6, 7, 8, 9}.isdisjoint(live) and set(range(5)) <= live
    assert mem.index.ntotal == 20 == mem.stats()["identities"]
    assert set(mem.a["id"][mem.rtm.members()].tolist()) <= live
    assert set(mem.a["id"][mem.tm.members()].tolist()) <= live
    # TM capacity: only TM sets are evicted
    mem2 = CompactMemory(MemoryConfig(delta=0.0, tm_capacity=10, max_store_batch=10))
    mem2.store(make(rng, 10))
    mem2.reduce(max_sets=10)
    mem2.store(make(rng, 10))
    mem2.store(make(rng, 3))
    assert mem2.tm_size == 10 and mem2.rtm_size == 10 and mem2.stats()["evictions"] == 3


def _bad_batches(rng):
    good = make(rng, 4)
    nan = make(rng, 4)
    nan.states[2, 1] = np.nan
    inf_lab = make(rng, 4)
    inf_lab.value_labels[3] = np.inf
    nolab = make(rng, 4)
    nolab.value_labels = np.zeros(0, np.float32)
    other_obs = make(rng, 4, obs=5)
    u8 = Transitions(np.zeros((4, 4), np.uint8), good.actions, good.rewards, np.zeros((4, 4), np.uint8),
                     good.terminated, good.truncated, value_labels=good.value_labels)
    wide_act = Transitions(good.states, np.zeros((4, 2), np.float32), good.rewards, good.next_states,
                           good.terminated, good.truncated, value_labels=good.value_labels)
    big = make(rng, 65)
    empty = make(rng, 0)
    ragged = Transitions(good.states, good.actions, good.rewards[:3], good.next_states,
                         good.terminated, good.truncated, value_labels=good.value_labels)
    return [nan, inf_lab, nolab, other_obs, u8, wide_act, big, empty, ragged, "not a batch"]


def test_bad_inputs_change_nothing(tmp_path):
    rng = np.random.default_rng(5)
    mem = CompactMemory(MemoryConfig(max_store_batch=64, storage_dir=str(tmp_path)))
    mem.store(make(rng, 8))
    before = mem.stats()
    arrays_before, _ = mem.export_state()
    for bad in _bad_batches(rng):
        with pytest.raises(MemoryInputError):
            mem.store(bad)
    assert mem.stats() == before
    arrays_after, _ = mem.export_state()
    for k in arrays_before:
        np.testing.assert_array_equal(arrays_before[k], arrays_after[k])
    lease = mem.begin_reduce(3)
    for ids, preds in ((lease.identity_ids, np.array([1.0, np.nan, 2.0])),
                       (lease.identity_ids, np.zeros(2)),
                       (np.r_[lease.identity_ids[:2], lease.identity_ids[0]], np.zeros(3))):  # a repeated id
        with pytest.raises(MemoryInputError):
            mem.commit_reduce(lease.reduction_id, ids, preds)
    mem.commit_reduce(lease.reduction_id, lease.identity_ids, np.zeros(3))
    with pytest.raises(MemoryInputError):
        mem.sample(1, source="nope")
    mem.close()
    mem2 = CompactMemory(MemoryConfig(max_store_batch=64, storage_dir=str(tmp_path)))
    assert mem2.stats()["identities"] == 8 and mem2.rtm_size == 3


def test_key_size_mismatch_and_config_checks():
    rng = np.random.default_rng(6)
    mem = CompactMemory(MemoryConfig(), key_size=99)
    with pytest.raises(MemoryInputError, match="key size"):
        mem.store(make(rng, 2))
    assert mem.stats()["identities"] == 0
    with pytest.raises(ConfigError):
        CompactMemory(MemoryConfig(max_store_batch=10, rtm_capacity=5))


def test_threads():
    rng = np.random.default_rng(7)
    mem = CompactMemory(MemoryConfig(delta=0.0))
    batches = [make(rng, 20) for _ in range(20)]
    errors = []

    def worker(bs):
        try:
            for b in bs:
                mem.store(b)
                mem.reduce(max_sets=5)
                if mem.rtm_size:
                    mem.sample(1)
        except Exception as e:  # pragma: no cover
            errors.append(e)

    th = [threading.Thread(target=worker, args=(batches[i::4],)) for i in range(4)]
    [x.start() for x in th]
    [x.join() for x in th]
    assert not errors and mem.stats()["identities"] == 400

"""The memory's budget: `rtm_capacity` live identities and the `removal` rule that decides which leave (lru, fifo,
reservoir, coverage), in-process and through a WAL replay. With keys far apart every transition is its own identity, so the
rules are those of the plain buffers they are named after."""
import numpy as np
import pytest

from comper_memory.core import CompactMemory, MemoryConfig
from comper_msgs_py.arrays import Transitions
from comper_msgs_py.params import config_from_dict


def batch(rng, n, obs=3):
    return Transitions(rng.standard_normal((n, obs)).astype(np.float32) * 10,
                       rng.standard_normal((n, 1)).astype(np.float32),
                       rng.standard_normal(n).astype(np.float32),
                       rng.standard_normal((n, obs)).astype(np.float32) * 10,
                       np.zeros(n, bool), np.zeros(n, bool), value_labels=np.zeros(n, np.float32))


def memory(cap, removal, **kw):
    return CompactMemory(MemoryConfig(rtm_capacity=cap, tm_capacity=max(cap, 64), max_store_batch=min(cap, 64),
                                      removal=removal, **kw))


def live_ids(mem) -> list[int]:
    return sorted(int(i) for i in mem.slots.ids_sorted)


def test_fifo_keeps_the_newest_identities_and_lru_the_recently_updated():
    rng = np.random.default_rng(0)
    first, second = batch(rng, 10), batch(rng, 10)
    fifo, lru = memory(12, "fifo"), memory(12, "lru")
    for mem in (fifo, lru):
        mem.store(first)
        mem.store(first.take(slice(0, 2)))          # a re-store updates ids 0 and 1, creates nothing
        res = mem.store(second)
        assert res.evicted == 8 and mem.slots.n_live == 12
    assert live_ids(fifo) == list(range(8, 20))                # the oldest created left
    assert live_ids(lru) == [0, 1] + list(range(10, 20))       # the least recently updated left
    assert fifo.stats()["evictions"] == 8


def test_reservoir_keeps_a_uniform_sample_of_every_identity_created():
    """Algorithm R over identities: after 600 identities into a budget of 60, each identity is kept with
    probability 1/10 whatever its age (counted over 40 seeds: the first, middle and last 200 ids hold about a third
    of the kept ones each), and the draw depends only on removal_seed and the ids."""
    kept = np.zeros(600)
    for seed in range(40):
        rng = np.random.default_rng(100)
        mem = memory(60, "reservoir", removal_seed=seed)
        for _ in range(10):
            mem.store(batch(rng, 60))
        ids = live_ids(mem)
        assert len(ids) == 60 and mem.stats()["evictions"] == 540
        kept[ids] += 1
    thirds = [kept[a:a + 200].sum() / kept.sum() for a in (0, 200, 400)]
    assert all(0.27 < t < 0.40 for t in thirds), thirds
    again = memory(60, "reservoir", removal_seed=39)
    rng = np.random.default_rng(100)
    for _ in range(10):
        again.store(batch(rng, 60))
    assert live_ids(again) == ids                              # the same draws from the same seed and ids


@pytest.mark.parametrize("removal", ["fifo", "reservoir", "coverage"])
def test_a_replayed_log_evicts_the_same_identities(tmp_path, removal):
    rng = np.random.default_rng(3)
    cfg = dict(storage_dir=str(tmp_path / "store"), snapshot_every=0)
    mem = memory(50, removal, **cfg)
    for _ in range(6):
        mem.store(batch(rng, 40))
    before = live_ids(mem)
    mem.close()
    back = memory(50, removal, **cfg)
    assert live_ids(back) == before and back.stats()["evictions"] == 6 * 40 - 50
    back.close()


def test_coverage_lets_identities_go_where_the_keys_are_densest():
    """A dense cluster of 900 identities and 100 spread far apart, into a budget of 500: the coverage rule evicts
    from the cluster and keeps every spread one (fifo and reservoir would keep about half of them); a store that
    needs more than its candidates still lands exactly on the capacity; the draws repeat with the seed."""
    rng = np.random.default_rng(7)
    dense = batch(rng, 900)
    for f in ("states", "next_states"):
        getattr(dense, f)[:] *= 1e-3
    spread = batch(rng, 100)
    for f in ("states", "next_states"):
        getattr(spread, f)[:] *= 100
    runs = []
    for _ in range(2):
        mem = CompactMemory(MemoryConfig(rtm_capacity=500, tm_capacity=10_000, max_store_batch=500,
                                         removal="coverage"))
        mem.store(spread)
        for k in range(0, 900, 100):
            mem.store(dense.take(slice(k, k + 100)))
        assert mem.slots.n_live == 500 and mem.stats()["evictions"] == 500
        runs.append(live_ids(mem))
    assert set(range(100)) <= set(runs[0])                     # every spread identity kept
    assert runs[0] == runs[1]


def test_an_unknown_rule_is_refused():
    with pytest.raises(ValueError, match="removal"):
        config_from_dict(MemoryConfig, {"removal": "random"})

"""The memory's rate limiter (Reverb's min size to sample + samples-per-insert with an error buffer),
in the core: both directions, the minimum size, calls that can never pass, nothing changed by a
held-back call, stats, and the balance after a recovery."""
import numpy as np
import pytest

from comper_memory.core import (CompactMemory, MemoryConfig, MemoryInputError, RateLimited,
                                RateLimiter)
from comper_msgs_py.params import ConfigError
from test_memory_core import make, relabel


def mem(tmp_path=None, **kw):
    return CompactMemory(MemoryConfig(**kw, **({"storage_dir": str(tmp_path)} if tmp_path else {})))


def test_limiter_arithmetic_matches_reverb_sample_to_insert_ratio():
    """spi 2, min size 10, buffer 8: offset 20, band [12, 28] of inserts x 2 - samples."""
    r = RateLimiter(min_size_to_sample=10, samples_per_insert=2.0, error_buffer=8.0)
    with pytest.raises(RateLimited, match="min_size_to_sample is 10"):
        r.check_sample(1, size=9)
    for _ in range(14):                      # free while below the minimum size, then up to 28
        r.check_insert(1, size=r.inserts)
        r.inserted(1)
    assert r.diff == 28
    with pytest.raises(RateLimited, match="waits for samples"):
        r.check_insert(1, size=14)
    r.check_sample(16, size=14)              # 28 - 16 = 12: at the lower edge
    r.sampled(16)
    with pytest.raises(RateLimited, match="waits for stores"):
        r.check_sample(1, size=14)
    r.check_insert(8, size=14)               # 12 + 16 = 28
    assert r.stats() == {"rate_inserts": 14, "rate_samples": 16, "samples_per_insert_held": 16 / 14,
                         "rate_limited_stores": 1, "rate_limited_samples": 2, "rate_relabelled": 0}
    with pytest.raises(MemoryInputError, match="could never pass"):
        r.check_insert(9, size=14)           # 18 > the whole window of 16
    with pytest.raises(MemoryInputError, match="could never pass"):
        r.check_sample(17, size=14)
    with pytest.raises(ValueError, match="at least max"):
        RateLimiter(0, 4.0, 3.0)


def test_memory_holds_the_ratio_and_a_held_back_call_changes_nothing():
    rng = np.random.default_rng(0)
    m = mem(samples_per_insert=1.0, rate_error_buffer=64.0, min_size_to_sample=32)
    with pytest.raises(RateLimited):
        m.sample(8, "tm")                    # empty: waits (not 'memory is empty')
    m.store(make(rng, 64))
    m.store(make(rng, 32))                   # 96 - 0 = 96 = offset 32 + buffer 64
    before = m.export_state()
    with pytest.raises(RateLimited, match="waits for samples"):
        m.store(make(rng, 1))
    after = m.export_state()
    assert before[1] == after[1] and all(np.array_equal(before[0][k], after[0][k]) for k in before[0])
    for _ in range(4):
        m.sample(32, "tm")                   # 96 - 128 = -32 = offset - buffer
    with pytest.raises(RateLimited, match="waits for stores"):
        m.sample(1, "tm")
    m.store(make(rng, 16))
    m.sample(16, "tm")
    s = m.rate_stats()
    assert (s["rate_inserts"], s["rate_samples"]) == (112, 144)
    assert s["rate_limited_stores"] == 1 and s["rate_limited_samples"] == 2
    assert s["samples_per_insert_held"] == pytest.approx(144 / 112)
    with pytest.raises(MemoryInputError, match="could never pass"):
        m.store(make(rng, 200))
    assert m.stats()["transitions_stored"] == 112


def test_without_a_rate_limit_nothing_waits_and_config_checks():
    rng = np.random.default_rng(1)
    m = mem()
    for _ in range(20):
        m.store(make(rng, 100))
    for _ in range(50):
        m.sample(64, "tm")
    assert m.rate_stats()["rate_limited_stores"] == m.rate_stats()["rate_limited_samples"] == 0
    with pytest.raises(ConfigError, match="rate_error_buffer"):
        MemoryConfig(samples_per_insert=2.0, rate_error_buffer=1.0).validate()


def test_a_recovered_memory_starts_at_the_balance_point(tmp_path):
    rng = np.random.default_rng(2)
    m = mem(tmp_path, samples_per_insert=1.0, rate_error_buffer=50.0, min_size_to_sample=20)
    m.store(make(rng, 60))
    m.close()
    m = mem(tmp_path, samples_per_insert=1.0, rate_error_buffer=50.0, min_size_to_sample=20)
    assert m.stats()["identities"] == 60 and m.rate.diff == 20     # offset 20 x 1
    m.sample(50, "tm")                                              # down to -30 = 20 - 50
    with pytest.raises(RateLimited):
        m.sample(1, "tm")
    m.close()


def test_a_relabel_store_is_neither_held_back_nor_counted_as_inserts():
    """restore_batch in async mode: fresh labels for stored transitions are not environment steps."""
    rng = np.random.default_rng(3)
    m = mem(samples_per_insert=1.0, rate_error_buffer=64.0, min_size_to_sample=32)
    t = make(rng, 96)
    m.store(t)                               # 96 = offset 32 + buffer 64: the next insert waits
    with pytest.raises(RateLimited, match="waits for samples"):
        m.store(make(rng, 1))
    r = m.store(relabel(t.take(slice(0, 64)), rng.standard_normal(64)), relabel=True)
    assert r.new_identities == 0             # they join their own sets (a label history), as in lock step
    s, st = m.rate_stats(), m.stats()
    assert (s["rate_inserts"], s["rate_relabelled"], s["rate_limited_stores"]) == (96, 64, 1)
    assert st["transitions_stored"] == 160 and st["identities"] == 96
    assert m.rate.diff == 96                 # the balance is that of the 96 inserts alone
    m.sample(64, "tm")                       # a sample releases as many inserts as before the relabel
    m.store(make(rng, 64))
    with pytest.raises(RateLimited, match="waits for samples"):
        m.store(make(rng, 1))

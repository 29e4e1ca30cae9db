"""Key normalisation (key_normalisation: running): moments, frozen map, re-indexing, snapshots and WAL replay."""
import numpy as np
import pytest

from comper_memory.core import CompactMemory, MemoryConfig, SnapshotError, exact_sq_dist, transition_keys
from comper_memory.core.key_norm import KeyNormaliser
from comper_msgs_py.params import ConfigError
from comper_msgs_py.arrays import Transitions

# per-dimension spread of the observations: one huge, one tiny, the rest ordinary
OBS_SCALE = np.array([1000.0, 0.001, 1.0, 1.0], np.float32)


def vec(rng, n, scale=OBS_SCALE):
    s = (rng.standard_normal((n, len(scale))) * scale).astype(np.float32)
    s2 = (rng.standard_normal((n, len(scale))) * scale).astype(np.float32)
    return Transitions(s, rng.standard_normal((n, 1)).astype(np.float32), rng.standard_normal(n).astype(np.float32),
                       s2, np.zeros(n, bool), np.zeros(n, bool), value_labels=rng.standard_normal(n).astype(np.float32))


def test_running_moments_equal_numpy_over_all_batches():
    rng = np.random.default_rng(0)
    kn = KeyNormaliser("running", growth=2.0)
    parts = [rng.standard_normal((n, 5)) * [1e3, 1e-3, 1, 5, 0] + [7, -2, 0, 1e4, 3] for n in (1, 7, 300, 2)]
    for p in parts:
        kn.observe(p.astype(np.float32))
    x = np.concatenate([p.astype(np.float32) for p in parts]).astype(np.float64)
    assert kn.n == len(x)
    np.testing.assert_allclose(kn.mu, x.mean(0), rtol=1e-12, atol=1e-9)
    np.testing.assert_allclose(kn.m2 / kn.n, x.var(0), rtol=1e-9, atol=1e-12)
    # observing alone never changes the map; the first freeze installs it
    head = x[:3]
    assert kn.mean is None and kn.apply(head) is head
    assert kn.maybe_freeze() and kn.updates == 1
    z = kn.apply(x.astype(np.float32)).astype(np.float64)
    np.testing.assert_allclose(z[:, :4].mean(0), 0, atol=1e-4)
    np.testing.assert_allclose(z[:, :4].std(0), 1, rtol=1e-4)
    # the constant dimension keeps scale 1: shifted, not blown up
    assert kn.scale[4] == 1.0 and np.allclose(z[:, 4], 0)
    # no new freeze until the moments have grown by key_norm_growth
    kn.observe(x[: len(x) - 1].astype(np.float32))
    assert not kn.maybe_freeze()
    kn.observe(x[:1].astype(np.float32))
    assert kn.maybe_freeze() and kn.updates == 2


def test_none_is_the_identity_and_keeps_no_moments():
    kn = KeyNormaliser("none")
    x = np.ones((3, 4), np.float32)
    kn.observe(x)
    assert not kn.maybe_freeze() and kn.apply(x) is x and kn.n == 0 and kn.arrays() == {}
    with pytest.raises(ValueError, match="key_normalisation"):
        KeyNormaliser("zscore")
    with pytest.raises(ConfigError, match="key_normalisation"):
        MemoryConfig(key_normalisation="zscore").validate()


def _near_copy(t: Transitions, shift: float) -> Transitions:
    """t with its first observation dimension (std 1000) moved by ``shift``."""
    s = t.states.copy()
    s[:, 0] += shift
    return Transitions(s, t.actions, t.rewards, t.next_states, t.terminated, t.truncated,
                       value_labels=t.value_labels)


@pytest.mark.parametrize("mode, joins", [("none", False), ("running", True)])
def test_delta_is_in_standard_deviations_after_the_first_reduction(mode, joins):
    """Moving a transition by 0.5 along a dimension whose spread is 1000 is far at delta 0.01 on raw
    keys (0.25 > 0.01) and near once keys are standardised ((0.5 / 1000)^2)."""
    mem = CompactMemory(MemoryConfig(delta=0.01, key_normalisation=mode))
    rng = np.random.default_rng(1)
    mem.store(vec(rng, 500))
    mem.reduce(max_sets=10)                      # freezes the running map (and re-indexes)
    probe = vec(rng, 1)
    first = mem.store(probe)
    again = mem.store(_near_copy(probe, 0.5))
    assert first.new_identities == 1
    assert bool(again.identity_ids[0] == first.identity_ids[0]) is joins
    assert mem.stats()["key_norm_updates"] == (1 if mode == "running" else 0)


def test_decisions_equal_brute_force_on_standardised_keys_across_reindexing():
    """Every store after each freeze joins exactly what a brute-force exact check over the frozen map's
    keys says; identical transitions stored before a freeze still join their identity after it."""
    cfg = MemoryConfig(delta=0.5, key_normalisation="running", key_norm_growth=2.0, index_min_train=16)
    mem = CompactMemory(cfg)
    rng = np.random.default_rng(2)
    kept = vec(rng, 40)
    updates = []
    for r in range(6):
        batch = vec(rng, 60 * (r + 1), scale=OBS_SCALE * 0.05)
        # brute force before the store: nearest existing identity within delta on the current map
        ids = mem.slots.live_ids()
        if len(ids):
            ex_keys = mem.slots.keys_of(ids).astype(np.float64)
            q = mem.key_norm.apply(transition_keys(batch.take(np.arange(1)), cfg.frame_scale))
            d = exact_sq_dist(ex_keys, q)
            expect = ids[np.argmin(d)] if d.min() <= cfg.delta else None
        res = mem.store(batch)
        if len(ids):
            got = res.identity_ids[0]
            assert (got == expect) if expect is not None else got not in set(ids.tolist())
        mem.store(kept)
        mem.reduce(max_sets=10_000)
        updates.append(mem.stats()["key_norm_updates"])
        # the kept transitions always join their own identities again: distance 0 under any map
        again = mem.store(kept)
        assert again.new_identities == 0 and again.similarity_hits == len(kept)
    assert updates[-1] >= 3 and updates == sorted(updates)


def _killed_and_recovered(cfg, seed, batches, size, reduce_every, max_sets):
    """A memory after ``batches`` stores (a reduction every ``reduce_every``) and the one a restart builds from its
    last snapshot and the WAL after it (what a SIGKILL leaves); both decide a new store alike."""
    from test_memory_storage import assert_same_state
    mem = CompactMemory(cfg)
    rng = np.random.default_rng(seed)
    for i in range(batches):
        mem.store(vec(rng, size))
        if i % reduce_every == reduce_every - 1:
            mem.reduce(max_sets=max_sets)
    assert mem.stats()["key_norm_updates"] >= 2
    again = CompactMemory(cfg)
    assert_same_state(mem, again)
    probe = vec(rng, 30)
    assert np.array_equal(mem.store(probe).identity_ids, again.store(probe).identity_ids)
    return mem


def test_snapshot_and_wal_replay_rebuild_the_normaliser(tmp_path):
    from test_memory_storage import assert_same_state
    cfg = MemoryConfig(storage_dir=str(tmp_path), snapshot_every=5, delta=0.3, key_normalisation="running",
                       index_min_train=16)
    mem = _killed_and_recovered(cfg, 3, 12, 50, 3, 40)
    path = str(tmp_path / "snap")
    mem.save_snapshot(path)
    third = CompactMemory(MemoryConfig(delta=0.3, key_normalisation="running", index_min_train=16))
    third.load_snapshot(path)
    assert_same_state(mem, third)
    for other in (MemoryConfig(delta=0.3), MemoryConfig(delta=0.3, key_normalisation="running", key_norm_growth=4.0)):
        with pytest.raises(SnapshotError, match="key normalisation"):
            CompactMemory(other).load_snapshot(path)


@pytest.mark.parametrize("mode", ["none", "running"])
def test_nn_quantile_puts_delta_at_the_quantile_of_nearest_neighbour_distances(mode):
    """delta_rule nn_quantile: after the first freeze (256 identities or more) the keys are scaled so that delta is
    the delta_quantile quantile of squared nearest-neighbour distances between live identities (all of them here:
    fewer than 1,024); identical transitions still join."""
    from comper_memory.core.key_norm import NN_MIN_IDENTITIES
    cfg = MemoryConfig(delta=1.0, key_normalisation=mode, delta_rule="nn_quantile", delta_quantile=0.25)
    mem = CompactMemory(cfg)
    rng = np.random.default_rng(4)
    mem.store(vec(rng, NN_MIN_IDENTITIES // 2))
    mem.reduce(max_sets=10)
    assert mem.stats()["key_norm_updates"] == 0            # too few identities to measure a spread
    mem.store(vec(rng, 400))
    mem.reduce(max_sets=10)
    assert mem.stats()["key_norm_updates"] == 1
    keys = mem.slots.keys_of(mem.slots.live_ids()).astype(np.float64)
    d = ((keys[:, None, :] - keys[None, :, :]) ** 2).sum(-1)
    np.fill_diagonal(d, np.inf)
    nn = d.min(1)
    assert abs(np.quantile(nn, 0.25) - cfg.delta) < 1e-6 * cfg.delta + 1e-9
    kept = mem.slots.live_ids()[:5]
    assert mem.store(mem.slots.reps(mem.slots.slots_of(kept), np.zeros(5, np.float32))).new_identities == 0


def test_nn_quantile_survives_snapshot_and_wal_replay_and_must_match(tmp_path):
    cfg = MemoryConfig(storage_dir=str(tmp_path), snapshot_every=4, delta=1.0, key_normalisation="running",
                       delta_rule="nn_quantile", delta_quantile=0.1, index_min_train=16)
    mem = _killed_and_recovered(cfg, 5, 10, 120, 2, 100)
    assert mem.stats()["similarity_hits"] > 0
    path = str(tmp_path / "snap")
    mem.save_snapshot(path)
    with pytest.raises(SnapshotError, match="key normalisation"):
        CompactMemory(MemoryConfig(delta=1.0, key_normalisation="running", delta_rule="nn_quantile",
                                   delta_quantile=0.2)).load_snapshot(path)


@pytest.mark.parametrize("bad", [dict(delta=0.0), dict(delta=1.0, delta_quantile=0.0),
                                 dict(delta=1.0, delta_quantile=1.0)])
def test_nn_quantile_needs_a_positive_delta_and_an_inner_quantile(bad):
    with pytest.raises(ConfigError, match="nn_quantile"):
        CompactMemory(MemoryConfig(delta_rule="nn_quantile", **bad))

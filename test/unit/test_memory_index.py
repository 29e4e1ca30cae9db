"""Exactness of the similarity decisions against a float64 brute-force sequential reference."""
import numpy as np
import pytest

from comper_memory.core import CompactMemory, MemoryConfig, exact_sq_dist, transition_keys
from comper_msgs_py.arrays import Transitions

FAST_INDEX = dict(index_min_train=64, index_list_size=16, index_rebuild_growth=2.0)


def make(rng, n, obs=5, dtype=np.float32, discrete=False):
    if dtype == np.uint8:
        s = rng.integers(0, 256, (n,) + obs, dtype=np.uint8)
        s2 = rng.integers(0, 256, (n,) + obs, dtype=np.uint8)
    else:
        s = rng.standard_normal((n, obs)).astype(np.float32)
        s2 = rng.standard_normal((n, obs)).astype(np.float32)
    a = rng.integers(0, 4, n) if discrete else rng.standard_normal((n, 2)).astype(np.float32)
    return Transitions(s, a, rng.standard_normal(n).astype(np.float32), s2,
                       np.zeros(n, bool), np.zeros(n, bool),
                       value_labels=rng.standard_normal(n).astype(np.float32))


class Reference:
    """Sequential float64 brute force: nearest live identity within delta, ties -> lowest id."""

    def __init__(self, delta, frame_scale=1 / 255):
        self.delta, self.fs = delta, frame_scale
        self.ids, self.keys, self.next_id = [], [], 0

    def store(self, t):
        keys = transition_keys(t, self.fs)
        out = []
        for k in keys:
            if self.keys:
                d = exact_sq_dist(np.asarray(self.keys), k[None, :])
                ok = np.flatnonzero(d <= self.delta)
                if len(ok):
                    ids = np.asarray(self.ids)[ok]
                    j = np.lexsort((ids, d[ok]))[0]
                    out.append(ids[j])
                    continue
            self.ids.append(self.next_id)
            self.keys.append(k)
            out.append(self.next_id)
            self.next_id += 1
        return np.asarray(out)

    def remove(self, ids):
        keep = [i for i, x in enumerate(self.ids) if x not in set(ids.tolist())]
        self.ids = [self.ids[i] for i in keep]
        self.keys = [self.keys[i] for i in keep]


def perturbed(rng, t, scale, frac=1.0):
    """Copies of t with small random perturbations on the states (some rows exact copies)."""
    s = t.states.copy()
    n = len(t)
    rows = rng.random(n) < frac
    s[rows] += (scale * rng.standard_normal(s[rows].shape)).astype(np.float32)
    return Transitions(s, t.actions.copy(), t.rewards.copy(), t.next_states.copy(), t.terminated,
                       t.truncated, value_labels=rng.standard_normal(n).astype(np.float32))


def one_pixel_off(t, rows):
    """Copies of the uint8 transitions t whose first state pixel is off by 1 in ``rows``
    (distance (1/255)^2 = 1.5e-5 from the original)."""
    s = t.states.copy()
    s[rows, 0, 0] ^= 1
    return Transitions(s, t.actions, t.rewards, t.next_states, t.terminated, t.truncated,
                       value_labels=t.value_labels)


@pytest.mark.parametrize("delta", [0.0, 1e-4, 1e-2, 0.5])
@pytest.mark.parametrize("seed", [0, 1])
def test_random_with_duplicates_and_near_duplicates(delta, seed):
    rng = np.random.default_rng(seed)
    mem = CompactMemory(MemoryConfig(delta=delta, **FAST_INDEX))
    ref = Reference(delta)
    base = make(rng, 150)
    for step in range(6):
        parts = [make(rng, 40), base.take(rng.integers(0, 150, 30)),
                 perturbed(rng, base.take(rng.integers(0, 150, 60)), np.sqrt(max(delta, 1e-6)) / 3)]
        t = Transitions.concatenate(parts).take(rng.permutation(130))
        got = mem.store(t).identity_ids
        np.testing.assert_array_equal(got, ref.store(t))
    assert mem.stats()["identities"] == len(ref.ids)
    assert mem.index.nlist > 1  # the partitioned path was exercised


@pytest.mark.parametrize("inside", [True, False])
def test_boundary_exactly_at_delta(inside):
    """Pairs whose float64 distance is exactly delta (inside) or one ulp above delta (outside)."""
    rng = np.random.default_rng(3)
    base = make(rng, 200)
    near = perturbed(rng, base, 1e-2)
    d = exact_sq_dist(transition_keys(base), transition_keys(near))
    target = float(np.sort(d)[100])
    delta = target if inside else float(np.nextafter(target, -np.inf))
    mem = CompactMemory(MemoryConfig(delta=delta, **FAST_INDEX))
    ref = Reference(delta)
    np.testing.assert_array_equal(mem.store(base).identity_ids, ref.store(base))
    got = mem.store(near).identity_ids
    np.testing.assert_array_equal(got, ref.store(near))
    k = int(np.flatnonzero(d == target)[0])
    assert (got[k] == k) == inside


def test_within_batch_sequential_semantics():
    rng = np.random.default_rng(5)
    one = make(rng, 1)
    t = Transitions.concatenate([one] * 5 + [make(rng, 3)] + [one] * 2)
    mem = CompactMemory(MemoryConfig(delta=0.0))
    r = mem.store(t)
    np.testing.assert_array_equal(r.identity_ids, [0, 0, 0, 0, 0, 1, 2, 3, 0, 0])
    assert r.new_identities == 4 and r.similarity_hits == 6


def test_within_batch_nearer_new_identity_wins():
    """Item 2 is within delta of existing identity 0 and of the new identity of item 1, but
    strictly nearer to the new one: it joins the new one (sequential semantics)."""
    rng = np.random.default_rng(6)
    base = make(rng, 1)
    mem = CompactMemory(MemoryConfig(delta=1.0))
    ref = Reference(1.0)
    ref.store(base)
    mem.store(base)
    a = base.states.copy()
    b1 = Transitions(a + np.float32(1.5), base.actions, base.rewards, base.next_states, base.terminated,
                     base.truncated, value_labels=base.value_labels)
    b2 = Transitions(a + np.float32(0.9), base.actions, base.rewards, base.next_states, base.terminated,
                     base.truncated, value_labels=base.value_labels)
    t = Transitions.concatenate([b1, b2])
    np.testing.assert_array_equal(mem.store(t).identity_ids, ref.store(t))


def test_atari_uint8_keys():
    rng = np.random.default_rng(7)
    obs = (84, 84)
    base = make(rng, 30, obs=obs, dtype=np.uint8, discrete=True)
    assert transition_keys(base).shape == (30, 14114)
    near = one_pixel_off(base, slice(0, None, 2))  # within 1e-4 of its original
    near.states[1::4, :3, :3] ^= 7  # far
    for delta in (0.0, 1e-4):
        mem = CompactMemory(MemoryConfig(delta=delta))
        ref = Reference(delta)
        for t in (base, near, Transitions.concatenate([near, base])):
            np.testing.assert_array_equal(mem.store(t).identity_ids, ref.store(t))
        assert mem.a["states"].dtype == np.uint8


def test_exact_after_evictions():
    rng = np.random.default_rng(8)
    mem = CompactMemory(MemoryConfig(delta=1e-2, rtm_capacity=300, max_store_batch=100, **FAST_INDEX))
    ref = Reference(1e-2)
    pool = make(rng, 400)
    for step in range(10):
        t = Transitions.concatenate([make(rng, 50), perturbed(rng, pool.take(rng.integers(0, 400, 50)), 0.03)])
        got = mem.store(t).identity_ids
        np.testing.assert_array_equal(got, ref.store(t))
        live = set(mem.slots.ids_sorted.tolist())
        ref.remove(np.asarray([i for i in ref.ids if i not in live]))
        assert mem.stats()["identities"] <= 300
        assert mem.index.ntotal == mem.stats()["identities"]
    assert mem.stats()["evictions"] > 0


# ---------------------------------------------------------------- grid engine / hybrid
import comper_memory.core.index as index_mod  # noqa: E402
import comper_memory.core.index_grid as index_grid  # noqa: E402


def _mem(engine, **kw):
    mem = CompactMemory(MemoryConfig(**{**FAST_INDEX, **kw}))
    mem.index_engine = engine
    return mem


@pytest.mark.parametrize("engine", ["grid", "ivf"])
@pytest.mark.parametrize("delta", [0.0, 1e-3, 0.3])
def test_engines_match_reference_with_evictions(engine, delta):
    """Both engines equal the float64 sequential reference, through evictions (lazy removal,
    stale-triggered rebuilds) and growth rebuilds (re-fitted PCA grid)."""
    rng = np.random.default_rng(11)
    mem = _mem(engine, delta=delta, rtm_capacity=250, max_store_batch=120)
    ref = Reference(delta)
    pool = make(rng, 300)
    for step in range(12):
        t = Transitions.concatenate([make(rng, 40), pool.take(rng.integers(0, 300, 40)),
                                     perturbed(rng, pool.take(rng.integers(0, 300, 40)),
                                               np.sqrt(max(delta, 1e-6)) / 2)])
        t = t.take(rng.permutation(len(t)))
        np.testing.assert_array_equal(mem.store(t).identity_ids, ref.store(t))
        live = set(mem.slots.ids_sorted.tolist())
        ref.remove(np.asarray([i for i in ref.ids if i not in live]))
        assert mem.index.ntotal == mem.stats()["identities"]
    assert mem.index.engine == engine and mem.stats()["evictions"] > 0
    if engine == "grid":
        assert mem.index.rebuilds >= 2


def test_grid_dense_cells_chunked_and_norm_growth(monkeypatch):
    """Many points in the same cells (huge delta, tiny candidate chunks) and keys whose norm
    later grows enough to force a coarser cell: still exact."""
    monkeypatch.setattr(index_grid, "_PAIR_CHUNK", 7)
    rng = np.random.default_rng(12)
    mem = _mem("grid", delta=2.0, max_key_abs=1e30)  # 1e7 values: beyond the default bound
    ref = Reference(2.0)
    small = make(rng, 60)
    small.states[:] *= np.float32(0.05)
    np.testing.assert_array_equal(mem.store(small).identity_ids, ref.store(small))
    big = make(rng, 60)
    big.states[:] *= np.float32(1e7)  # norm growth: projection error bound exceeds the cell
    before = mem.index.rebuilds
    np.testing.assert_array_equal(mem.store(big).identity_ids, ref.store(big))
    assert mem.index.rebuilds > before
    mix = Transitions.concatenate([perturbed(rng, small, 0.3), perturbed(rng, big, 0.3)])
    np.testing.assert_array_equal(mem.store(mix).identity_ids, ref.store(mix))


def test_within_batch_chain_is_not_transitive():
    """A creates; B (near A) joins A; C is near B but not near A: C creates (B is no identity)."""
    base = make(np.random.default_rng(13), 1)
    rows = []
    for shift in (0.0, 0.8, 1.6):
        s = base.states.copy()
        s[:, 0] += np.float32(shift)
        rows.append(Transitions(s, base.actions, base.rewards, base.next_states, base.terminated,
                                base.truncated, value_labels=base.value_labels))
    t = Transitions.concatenate(rows)
    for engine in ("grid", "ivf"):
        mem = _mem(engine, delta=1.0)
        np.testing.assert_array_equal(mem.store(t).identity_ids, [0, 0, 1])


def test_grid_snapshot_restore_rebuilds_index(tmp_path):
    rng = np.random.default_rng(14)
    mem = _mem("grid", delta=1e-2)
    base = make(rng, 200)
    mem.store(base)
    mem.save_snapshot(str(tmp_path / "s"))
    other = _mem("grid", delta=1e-2)
    other.load_snapshot(str(tmp_path / "s"))
    q = perturbed(rng, base.take(np.arange(0, 200, 3)), 0.02)
    np.testing.assert_array_equal(mem.store(q).identity_ids, other.store(q).identity_ids)
    assert other.index.ntotal == other.stats()["identities"]


@pytest.mark.parametrize("engine, cls_name", [("grid", "GridIndex"), ("faiss_ivf", "ExactIndex")])
def test_index_engine_parameter_selects_the_engine_and_decisions_agree(engine, cls_name):
    rng = np.random.default_rng(7)
    t = make(rng, 300)
    t = Transitions.concatenate([t, t.take(np.arange(100))])  # 100 exact re-stores
    mem = CompactMemory(MemoryConfig(delta=1e-4, index_engine=engine))
    res = mem.store(t)
    assert type(mem.index).__name__ == cls_name
    assert res.new_identities == 300
    np.testing.assert_array_equal(res.identity_ids[300:], res.identity_ids[:100])


def test_grid_filter_dims_cut_exact_rechecks_and_stay_exact(monkeypatch):
    """Frames that differ along many directions (two bright pixels each, as sprites do) pile up in
    the cells of a 3-d projection; filtering on 8 projected coordinates leaves far fewer exact
    re-checks, and decisions equal the brute-force reference either way."""
    checked = []
    orig = index_mod.GridIndex.resolve

    def spy(self, *args, **kwargs):
        res = orig(self, *args, **kwargs)
        checked.append(res.candidates_checked)
        return res

    monkeypatch.setattr(index_mod.GridIndex, "resolve", spy)
    rng = np.random.default_rng(21)
    n, side = 600, 12
    s = np.full((n, side, side), 40, np.uint8)
    for _ in range(2):
        s.reshape(n, -1)[np.arange(n), rng.integers(0, side * side, n)] = rng.integers(100, 256, n)
    t = Transitions(s, np.zeros(n, np.int64), np.zeros(n, np.float32), s.copy(), np.zeros(n, bool),
                    np.zeros(n, bool), value_labels=np.zeros(n, np.float32))
    per_dims = {}
    for dims in (3, 8):
        checked.clear()
        mem = CompactMemory(MemoryConfig(delta=1e-4, index_projection_dim=dims, index_min_train=64))
        ref = Reference(1e-4)
        for lo in range(0, n, 50):
            part = t.take(np.arange(lo, lo + 50))
            again = t.take(rng.integers(0, lo + 50, 20))  # re-stores join their own identity
            for batch in (part, again):
                np.testing.assert_array_equal(mem.store(batch).identity_ids, ref.store(batch))
        assert mem.index.mf == dims
        per_dims[dims] = sum(checked[::2])  # the batches of new frames: nothing to find but exact copies
    assert per_dims[8] * 3 < per_dims[3], per_dims


def test_grid_top_corner_cells_are_found():
    """Keys whose projections clip to the largest cell index on every axis (a first batch with a
    huge coordinate fixes the grid's extent, later keys lie beyond it): their code is the largest
    one, and the end of its code range must not wrap around int64. Decisions equal the reference."""
    def batch(base, n=32, seed=0):
        rng = np.random.default_rng(seed)
        s = rng.normal(size=(n, 6)).astype(np.float32)
        s[:, 0] = (base + np.arange(n)).astype(np.float32)
        return Transitions(s, rng.uniform(-1, 1, (n, 2)).astype(np.float32), rng.normal(size=n).astype(np.float32),
                           rng.normal(size=(n, 6)).astype(np.float32), np.zeros(n, bool), np.zeros(n, bool),
                           value_labels=np.zeros(n, np.float32))

    for sign in (1.0, -1.0):
        mem, ref = CompactMemory(MemoryConfig(delta=1e-4, max_key_abs=1e30)), Reference(1e-4)
        parts = [batch(sign * 2e6, seed=1), batch(sign * 1e6, seed=2), batch(sign * 5e5, seed=3)]
        for t in parts + parts:                      # the second pass re-stores every transition
            np.testing.assert_array_equal(mem.store(t).identity_ids, ref.store(t))
        assert mem.stats()["identities"] == 96


def test_grid_refit_on_wide_keys_streams_the_sample_in_blocks(monkeypatch):
    """Atari-width keys (14,114 values): the PCA refit gets the sample in row blocks of at most
    ``(1 << 22) // key_dim`` rows, never the whole sample at full width (20,000 keys of 4 stacked
    frames would be 4.5 GB as float32), and the decisions stay those of the brute-force reference."""
    from comper_memory.core import grid_cells
    seen = []
    fit = grid_cells.GridCells.fit_directions

    def spy(self, blocks, rng):
        blocks = list(blocks)
        seen.append([len(b) for b in blocks])
        return fit(self, blocks, rng)

    monkeypatch.setattr(grid_cells.GridCells, "fit_directions", spy)
    rng = np.random.default_rng(15)
    base = make(rng, 400, obs=(84, 84), dtype=np.uint8, discrete=True)
    step = (1 << 22) // 14114
    near = one_pixel_off(base, slice(0, None, 3))  # within delta of its original
    mem, ref = _mem("grid", delta=1e-4), Reference(1e-4)
    for t in (base, near):
        np.testing.assert_array_equal(mem.store(t).identity_ids, ref.store(t))
    assert seen, "no refit happened"
    assert max(len(b) for b in seen) > 1 and max(max(b) for b in seen) <= step
    assert sum(seen[-1]) == mem.index.n_at_build

"""Limits of the compact memory's grid index (issue 57): any ``max_key_abs`` up to its maximum keeps
stores as cheap as without huge values, and a batch whose keys jump outside the fitted grid costs work
linear in its size. Costs are asserted as counts (candidate pairs scanned, exact re-checks, rebuilds),
never as times; decisions are checked against the brute-force reference of test_memory_index."""
from __future__ import annotations

import numpy as np
import pytest

from comper_memory.core import CompactMemory, MemoryConfig, MemoryInputError, grid_cells, transition_keys
from comper_msgs_py.arrays import Transitions
from comper_msgs_py.params import ConfigError, config_from_dict
from test_memory_index import FAST_INDEX, Reference, make, perturbed


def shifted(t: Transitions, by: float) -> Transitions:
    """t with every observation value moved by ``by`` (a batch that jumps away from the grid)."""
    return Transitions(t.states + np.float32(by), t.actions, t.rewards, t.next_states + np.float32(by),
                       t.terminated, t.truncated, value_labels=t.value_labels)


def scanned_per_transition(mem, batch) -> float:
    before = mem.index.scanned
    mem.store(batch)
    return (mem.index.scanned - before) / len(batch)


def exact_checks_per_transition(mem, batch) -> float:
    y = mem.index._zproj(transition_keys(batch))
    return sum(len(c) for _, c in mem.index.candidates_of(y)) / len(batch)


# ----------------------------------------------------------------------------- max_key_abs (item 1)
def test_max_key_abs_beyond_its_maximum_is_a_config_error():
    """Parameters (ROS, YAML, command line) accept max_key_abs up to 3e38 and refuse more."""
    assert config_from_dict(MemoryConfig, {"max_key_abs": 3e38}).max_key_abs == 3e38
    with pytest.raises(ConfigError, match="max_key_abs.*above the maximum"):
        config_from_dict(MemoryConfig, {"max_key_abs": 3.4e38})


def test_refusal_at_the_largest_bound_names_the_value_and_the_range():
    """At max_key_abs 3e38, float32(3e38) = 3.0000000054977558e38 is beyond it: the refusal names that
    value and its position (a float32 comparison named position 0 and a value inside the bound), and
    the range the bound may be raised to."""
    mem = CompactMemory(MemoryConfig(max_key_abs=3e38))
    bad = make(np.random.default_rng(1), 4)
    bad.states[2, 3] = np.float32(3e38)
    with pytest.raises(MemoryInputError, match=r"transition 2 has key value 3e\+38 \(state, key position 3\)"
                                               r".*raise max_key_abs, at most 3e\+38"):
        mem.store(bad)
    assert mem.stats()["identities"] == 0


@pytest.mark.parametrize("value", [1e20, 3e37])
def test_a_huge_value_under_a_raised_bound_does_not_slow_later_stores(value):
    """Issue 57: with max_key_abs raised (1e30, as the refusal suggested) one stored 1e20 value made
    every cell 5e6 wide, so each store scanned and re-checked every identity. Now the huge key is
    indexed apart (by its norm): the cells, the scans and the re-checks equal those of a memory without it."""
    costs, cells = {}, {}
    for poisoned in (False, True):
        rng = np.random.default_rng(10)
        mem = CompactMemory(MemoryConfig(max_key_abs=3e38))
        if poisoned:
            p = make(rng, 1)
            p.states[0, 3] = np.float32(value)
            mem.store(p)
        for _ in range(12):
            mem.store(make(rng, 512))
        cells[poisoned] = mem.index.grid.cell.copy()
        costs[poisoned] = (exact_checks_per_transition(mem, make(rng, 64)),
                           np.mean([scanned_per_transition(mem, make(rng, 64)) for _ in range(10)]))
    np.testing.assert_allclose(cells[True], cells[False], rtol=1e-6)   # before: 5e6 (1e20)
    assert costs[True][0] <= costs[False][0] + 1, costs        # before: 6,144 (every identity)
    assert costs[True][1] <= 2 * costs[False][1] + 1, costs
    assert mem.index.n_wide == 1
    assert mem.store(p).new_identities == 0                    # the huge key is still found


def test_huge_keys_are_decided_exactly():
    """Keys with values from 1e9 to 1e30, their copies and copies changed far below delta (in a small
    value) or beyond it: the decisions equal the brute-force reference."""
    rng = np.random.default_rng(2)
    mem, ref = CompactMemory(MemoryConfig(delta=1e-4, max_key_abs=3e38, **FAST_INDEX)), Reference(1e-4)
    base = make(rng, 300)
    base.states[:, 0] = (10.0 ** rng.integers(9, 31, 300)).astype(np.float32) * rng.choice([-1, 1], 300)
    base.states[::7, 0] = 0.0                          # and some ordinary keys among them
    for t in (base, perturbed(rng, base, 3e-3, 0.5), perturbed(rng, base, 3e-2, 0.5), base):
        np.testing.assert_array_equal(mem.store(t).identity_ids, ref.store(t))
    assert mem.index.n_wide > 0


# ----------------------------------------------------------------------------- linear stores (item 2)
def test_a_batch_that_jumps_outside_the_grid_costs_linear_work():
    """Issue 57: keys outside the fitted extent were clipped into the edge cells, so a batch whose keys
    all jumped away (every observation value + 1e6) piled into one cell and scanned all its pairs
    (16,384 transitions: 268 M pairs, 29 s). Cell indices now wrap, so the batch spreads over the cells
    as stored keys do: the pairs scanned per transition stay a small constant for every batch size, and
    the index does not rebuild per transition."""
    per = {}
    for n in (1024, 4096):
        rng = np.random.default_rng(3)
        mem = CompactMemory(MemoryConfig())
        for _ in range(4):
            mem.store(make(rng, 1024))
        rebuilds = mem.index.rebuilds
        per[n] = scanned_per_transition(mem, shifted(make(rng, n), 1e6))   # before: n - 1
        assert mem.index.rebuilds - rebuilds <= 2
        again = mem.store(shifted(make(np.random.default_rng(99), 1), 0))  # a later ordinary store
        assert again.new_identities == 1
    assert per[1024] <= 4 and per[4096] <= 4, per


def test_chunked_and_whole_stores_of_a_jumping_batch_decide_alike():
    """The same jumping batch stored whole and in chunks of 256: the same identities."""
    rng = np.random.default_rng(4)
    fill, jump = make(rng, 2048), shifted(make(rng, 2048), 1e6)
    jump = Transitions.concatenate([jump, perturbed(rng, jump, 2e-3)])
    a, b = CompactMemory(MemoryConfig()), CompactMemory(MemoryConfig())
    a.store(fill)
    b.store(fill)
    whole = a.store(jump).identity_ids
    op = b.begin_store(jump, chunk=256)
    while not op.done:
        op.step()
    np.testing.assert_array_equal(op.result().identity_ids, whole)


# ----------------------------------------------------------------------------- exactness at the new seams
def test_keys_spread_over_many_wraps_are_decided_exactly():
    """Keys spread over ~100 periods of the wrapped cell index (a value uniform in +-1e6 at cells of
    0.01), with near copies: the decisions equal the brute-force reference."""
    rng = np.random.default_rng(5)
    mem, ref = CompactMemory(MemoryConfig(delta=1e-4, **FAST_INDEX)), Reference(1e-4)
    base = make(rng, 400)
    base.states[:, 0] = rng.uniform(-1e6, 1e6, 400).astype(np.float32)
    for t in (base.take(np.arange(200)), base):
        np.testing.assert_array_equal(mem.store(t).identity_ids, ref.store(t))
    for t in (perturbed(rng, base, 3e-3, 0.5), perturbed(rng, base, 3e-3, 0.5)):
        np.testing.assert_array_equal(mem.store(t).identity_ids, ref.store(t))


def test_wrapped_neighbour_at_either_end_of_the_last_axis_is_proposed():
    """Two points one cell apart across the wrap of the last cell axis (indices GRID_MAX and 0): each
    one's neighbour code ranges hold the other's code."""
    g = grid_cells.GridCells(13, 1e-4, grid_dims=3, filter_dims=8, seed=0)
    z0 = np.random.default_rng(6).standard_normal((100, 8))
    g.fit(z0, np.linalg.norm(z0, axis=1))
    period = grid_cells.PERIOD
    z = np.zeros((2, 8))
    for t_last in (period - 0.5, 3 * period - 0.5):       # cell PERIOD-1 = GRID_MAX, next one wraps to 0
        for k in range(3):
            z[:, k] = g.origin[k] + g.cell[k] * 7.5
        z[0, 2] = g.origin[2] + g.cell[2] * t_last
        z[1, 2] = z[0, 2] + g.cell[2] * 0.9
        cells = g.cells(z)
        assert sorted(cells[:, 2].tolist()) == [0, grid_cells.GRID_MAX]
        codes = g.code(z)
        lo, hi, valid = g.ranges(cells)
        for a, b in ((0, 1), (1, 0)):
            assert (valid[a] & (lo[a] <= codes[b]) & (codes[b] <= hi[a])).any()


@pytest.mark.parametrize("seam", ["norm_cap", "raw_limit"])
def test_keys_on_both_sides_of_the_grid_seam_are_decided_exactly(monkeypatch, seam):
    """The seam between grid keys and wide keys moved into the middle of ordinary keys (a norm cap at
    the median norm, or an exact-wrap range two cells from the centre): near copies on either side of
    it, inside one batch and across batches, are decided as by the brute-force reference."""
    if seam == "norm_cap":
        fit = grid_cells.GridCells.fit

        def low_cap(self, z, norms):
            fit(self, z, norms)
            self.norm_cap = 3.5            # keys of 13 values N(0, 1): median norm ~3.5

        monkeypatch.setattr(grid_cells.GridCells, "fit", low_cap)
    else:
        monkeypatch.setattr(grid_cells, "RAW_LIMIT", float(grid_cells.GRID_MAX // 2 + 2))
    rng = np.random.default_rng(7)
    mem, ref = CompactMemory(MemoryConfig(delta=0.5, **FAST_INDEX)), Reference(0.5)
    base = make(rng, 300)
    for t in (base, perturbed(rng, base, 0.2, 0.7), perturbed(rng, base, 0.4),
              Transitions.concatenate([make(rng, 100), perturbed(rng, base, 0.3)])):
        np.testing.assert_array_equal(mem.store(t).identity_ids, ref.store(t))
    n_wide = mem.index.n_wide
    assert 0 < n_wide < mem.index.ntotal + mem.index.stale, n_wide

"""benchmarks/atari_policy_check.py: the value-scale columns (max_a Q against the discounted return collected from
the same states) on hand-computed episodes."""
import numpy as np
import pytest

from scaffolding import load_benchmark


def _check():
    return load_benchmark("atari_policy_check")


def test_discounted_returns_run_to_the_episode_end():
    pc = _check()
    assert pc.discounted_returns([0.0, 1.0, 0.0, 1.0], 0.5) == pytest.approx([0.625, 1.25, 0.5, 1.0])
    assert pc.discounted_returns([], 0.99) == []


def test_value_scale_compares_q_with_the_returns_of_the_same_states():
    pc = _check()
    g = pc.discounted_returns([0.0, 0.0, 1.0, 0.0, 1.0], 0.9)
    offset = [x + 5.0 for x in g]                 # a Q that holds the return plus a constant
    r = pc.value_scale(offset, g)
    assert r["value_states"] == 5 and r["v_mean"] == pytest.approx(np.mean(g) + 5.0)
    assert r["mc_return_mean"] == pytest.approx(np.mean(g)) and r["mc_return_max"] == pytest.approx(max(g))
    assert r["v_mc_corr"] == pytest.approx(1.0) and r["v_std"] == pytest.approx(np.std(g))
    flat = pc.value_scale([6.0] * 5, g)           # one number in every state: no correlation defined
    assert np.isnan(flat["v_mc_corr"]) and flat["v_std"] == 0.0
    assert pc.value_scale([1.0], [1.0]) == {"value_states": 1}

"""Offline evaluation: the thesis's summaries, MC returns, episode reconstruction, bag reading."""
from __future__ import annotations

import json
import math

import numpy as np
import pytest

from comper_agent.offline import runs as offline

from comper_agent.offline import value_checks
from comper_agent.offline.runs import (discounted_returns, final_performance, reconstruct_episodes,
                                  tercile_summaries)
from scaffolding import synthetic_run
from comper_msgs_py.arrays import Transitions


def test_last_10_and_last_3_rule():
    r = list(range(30))
    assert final_performance(r) == (np.mean(range(20, 30)), 10)
    assert final_performance(r[:25]) == (np.mean(range(15, 25)), 10)      # 25 episodes: last 10
    assert final_performance(r[:24]) == (np.mean([21, 22, 23]), 3)        # under 25: last 3
    assert final_performance([5.0, 7.0]) == (6.0, 2)
    m, n = final_performance([])
    assert math.isnan(m) and n == 0


def test_terciles():
    # 30 episodes ending every 10 frames up to 300: terciles end at 100, 200, 300
    prog = np.arange(1, 31) * 10
    ret = np.arange(30, dtype=float)
    t = tercile_summaries(prog, ret)
    assert [x["end"] for x in t] == [100.0, 200.0, 300.0]
    assert t[0]["mean"] == np.mean(ret[5:10]) and t[0]["n"] == 5      # episodes ending <= 100: 0..9
    assert t[1]["mean"] == np.mean(ret[15:20])
    assert t[2]["mean"] == np.mean(ret[25:30])
    # under 25 episodes: last 3; an explicit budget (the last episode finishes past it)
    prog = np.array([40, 90, 130, 170, 260, 310])
    t = tercile_summaries(prog, np.arange(6.0), budget=300)
    assert t[0]["mean"] == np.mean([0, 1]) and t[0]["n"] == 2
    assert t[1]["mean"] == np.mean([1, 2, 3])
    assert t[2]["mean"] == np.mean([3, 4, 5])


def test_discounted_returns():
    r = np.array([1.0, 1.0, 1.0, 2.0, 2.0])
    ends = np.array([False, False, True, False, True])
    g = discounted_returns(r, ends, 0.5)
    np.testing.assert_allclose(g, [1 + 0.5 + 0.25, 1 + 0.5, 1.0, 2 + 1.0, 2.0])
    np.testing.assert_allclose(discounted_returns(r, ends, 1.0), [3, 2, 1, 4, 2])


def test_reconstruct_episodes_by_ids_and_flags():
    t, summ = synthetic_run(3000, seed=3)
    perm = np.random.default_rng(0).permutation(len(t))   # order in the bag does not matter
    eps = reconstruct_episodes(t.take(perm))
    assert [e.episode_id for e in eps] == [s["episode_id"] for s in summ]
    assert [e.length for e in eps] == [s["length"] for s in summ]
    assert all(e.contiguous for e in eps)
    assert [e.terminated for e in eps] == [s["terminated"] for s in summ]
    for e, s in zip(eps, summ):
        assert e.episode_return == pytest.approx(s["episode_return"], rel=1e-5, abs=1e-4)
    # without episode ids: cut at terminated | truncated
    bare = Transitions(t.states, t.actions, t.rewards, t.next_states, t.terminated, t.truncated)
    assert [e.length for e in reconstruct_episodes(bare)] == [s["length"] for s in summ]
    # a gap in the steps is reported
    gap = t.take(np.delete(np.arange(len(t)), 5))
    assert not reconstruct_episodes(gap)[0].contiguous


def test_incomplete_last_episode():
    t, summ = synthetic_run(1000, seed=2)
    cut = t.take(slice(0, len(t) - 3))
    eps = reconstruct_episodes(cut)
    assert not eps[-1].complete and all(e.complete for e in eps[:-1])


def _run_with(returns, frames, evals=()):
    run = offline.RunData("r", env_id="Hopper-v4", algorithm="comcact")
    for i, (r, f) in enumerate(zip(returns, frames)):
        run.episodes.append(offline.EpisodeRecord("r", "Hopper-v4", "train", i, r, 10, 10, True, False, f, f, 0.0))
    for s, vals in evals:
        run.evaluations.append(offline.EvalPoint("r", "comcact", "Hopper-v4", s, list(vals), [1] * len(vals),
                                                 float(np.mean(vals)), float(np.std(vals))))
    return run


def test_run_and_group_summaries():
    a = offline.run_summary(_run_with(np.arange(30.0), np.arange(1, 31) * 10, [(100, [1, 3]), (300, [5, 7])]))
    b = offline.run_summary(_run_with(np.arange(30.0) + 2, np.arange(1, 31) * 10, [(100, [3, 5]), (300, [9, 11])]))
    assert a["final"]["mean"] == np.mean(range(20, 30)) and a["final_eval"] == 6.0
    (g,) = offline.group_summaries([a, b])
    assert g["final"]["mean"] == pytest.approx(np.mean(range(20, 30)) + 1) and g["final"]["std"] == pytest.approx(1.0)
    assert [c["mean"] for c in g["eval_curve"]] == [3.0, 8.0]
    assert g["final_eval"]["std"] == pytest.approx(2.0)


def test_eval_points_from_eval_episodes():
    run = _run_with([1.0], [10])
    for i, r in enumerate([2.0, 4.0, 6.0]):
        run.episodes.append(offline.EpisodeRecord("r", "H", "eval", i, r, 1, 1, True, False, 5000, 5000, 0.0))
    (p,) = offline.eval_points(run)
    assert p["global_step"] == 5000 and p["mean"] == 4.0 and p["n"] == 3


def test_cross_check_flags_a_wrong_return():
    t, summ = synthetic_run(2000, seed=4)
    run = offline.RunData("synthetic", transitions=t)
    for s in summ:
        run.episodes.append(offline.EpisodeRecord("synthetic", "H", "train", s["episode_id"], s["episode_return"],
                                                  s["length"], s["frames"], s["terminated"], s["truncated"],
                                                  s["global_step"], s["global_frames"], 0.0))
    cc = offline.cross_check(run)
    assert cc["checked"] == len(summ) and not cc["mismatches"] and cc["max_abs_diff"] < 1e-3
    run.episodes[2].episode_return += 0.5
    assert [m["episode_id"] for m in offline.cross_check(run)["mismatches"]] == [2]


def test_q_vs_mc_and_fqe_with_a_checkpoint(tmp_path):
    torch = pytest.importorskip("torch")
    from comper_agent.core.checkpoint import save_checkpoint
    from comper_agent.core.comcact import ComcactLearner
    from comper_agent.core.config import DDPGConfig
    t, _ = synthetic_run(1500, seed=5, obs_dim=4, action_dim=2)
    learner = ComcactLearner(DDPGConfig(actor_hidden=[32, 16], critic_hidden=[32, 16]), 4, [-1, -1], [1, 1])
    path = save_checkpoint(tmp_path / "ckpt.pt", {"learner": learner.state_dict(), "counters": {"step": 0}})
    pol = value_checks.load_policy(path)
    q_ref = learner.q_values(t.states[:50], t.actions[:50]).reshape(-1)
    np.testing.assert_allclose(pol.q_values(t.states[:50], t.actions[:50]), q_ref, rtol=1e-5, atol=1e-6)
    res = value_checks.q_vs_mc(pol, t, gamma=0.9)
    assert res["n"] == len(t) and np.isfinite(res["bias"]) and -1 <= res["corr"] <= 1
    # reward 1 on average, gamma 0.9: MC returns near 10 away from the episode ends
    assert 5 < res["mean_mc"] < 10.5
    f = value_checks.fitted_q_evaluation(pol, t, gamma=0.9, updates=300)
    assert np.isfinite(f["fqe_value"]) and f["initial_states"] > 0
    # nets without batch norm, action after the second hidden layer: rebuilt from the checkpoint alone
    for kw in ({"batch_norm": False}, {"batch_norm": False, "critic_action_input": "output"}):
        plain = ComcactLearner(DDPGConfig(actor_hidden=[32, 16], critic_hidden=[32, 16], **kw), 4, [-1, -1], [1, 1])
        p2 = save_checkpoint(tmp_path / "plain.pt", {"learner": plain.state_dict(), "counters": {"step": 0}})
        np.testing.assert_allclose(value_checks.load_policy(p2).q_values(t.states[:20], t.actions[:20]),
                                   plain.q_values(t.states[:20], t.actions[:20]).reshape(-1), rtol=1e-5, atol=1e-6)

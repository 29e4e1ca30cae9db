"""n-step returns (``n_step``): the DQN replay's windows, the COMPER variants' stored windows
(memory_schedule.NStepWindows) and the learner's targets for both, each against a reference written
out here from the episodes."""
import sys
from pathlib import Path

_SRC = Path(__file__).resolve().parents[2] / "src"
for _p in (_SRC / "comper_msgs", _SRC / "comper_agent"):
    if str(_p) not in sys.path:
        sys.path.insert(0, str(_p))

import numpy as np
import pytest
import torch

from comper_msgs_py.arrays import Transitions
from comper_msgs_py.params import config_from_dict
from comper_agent.core.comper import ComperLearner
from comper_agent.core.config import ComperConfig
from comper_agent.core.memory_schedule import NStepWindows, Row
from comper_agent.core.replay import FrameReplay, NStepRewards, ReplayBuffer

torch.set_num_threads(1)


def _vector_episodes(lengths_and_ends, seed=0):
    """Time-ordered transitions of episodes ending 'terminated' or 'truncated'; state t of an episode
    is [episode, t] so that every next state names where it comes from."""
    rng = np.random.default_rng(seed)
    rows = []
    for e, (length, end) in enumerate(lengths_and_ends):
        for t in range(length):
            last = t == length - 1
            rows.append(dict(s=[e, t], ns=[e, t + 1], a=int(rng.integers(2)), r=float(rng.integers(-3, 4)),
                             term=last and end == "terminated", trunc=last and end == "truncated"))
    return rows


def _reference_window(rows, i, n):
    """The window a transition starts, from the time-ordered list of what the buffer holds."""
    out = [rows[i]]
    while (len(out) < n and not (out[-1]["term"] or out[-1]["trunc"]) and i + len(out) < len(rows)):
        out.append(rows[i + len(out)])
    return out


def test_replay_windows_stop_at_episode_ends_and_the_newest_transition_across_a_wrapped_ring():
    rows = _vector_episodes([(6, "terminated"), (9, "truncated"), (4, "terminated"), (12, "truncated"),
                             (5, "terminated")])           # 36 transitions into capacity 25: the ring wraps
    rb = ReplayBuffer(25, (2,), seed=0)
    for r in rows:
        rb.add(Transitions(states=np.array([r["s"]], np.float32), actions=np.array([r["a"]], np.float32),
                           rewards=np.array([r["r"]], np.float32), next_states=np.array([r["ns"]], np.float32),
                           terminated=np.array([r["term"]]), truncated=np.array([r["trunc"]])))
    kept = rows[-25:]                                      # age order: rb.pos is the oldest slot
    slots = (rb.pos + np.arange(25)) % 25
    n = 4
    windows, last = rb._windows(slots, n)
    for k, slot in enumerate(slots):
        want = _reference_window(kept, k, n)
        assert windows.lengths[k] == len(want)
        np.testing.assert_array_equal(windows.rewards[k, :len(want)], [w["r"] for w in want])
        assert not windows.rewards[k, len(want):].any()
        np.testing.assert_array_equal(rb.next_states[last[k]], want[-1]["ns"])
        assert rb.terminated[last[k]] == want[-1]["term"] and rb.truncated[last[k]] == want[-1]["trunc"]
    assert windows.lengths[-1] == 1 and windows.lengths[-2] == 2     # the newest transitions: short windows
    assert set(windows.lengths) == {1, 2, 3, 4}


def test_sample_with_n_step_returns_the_window_ends_and_one_step_sampling_is_unchanged():
    rows = _vector_episodes([(30, "terminated"), (30, "truncated")], seed=3)
    make = lambda: ReplayBuffer(100, (2,), seed=7)
    a, b = make(), make()
    for buf in (a, b):
        for r in rows:
            buf.add(Transitions(states=np.array([r["s"]], np.float32), actions=np.array([r["a"]], np.float32),
                                rewards=np.array([r["r"]], np.float32), next_states=np.array([r["ns"]], np.float32),
                                terminated=np.array([r["term"]]), truncated=np.array([r["trunc"]])))
    one = a.sample(16)
    batch, windows = b.sample(16, n_step=5)
    np.testing.assert_array_equal(batch.states, one.states)          # the same draws
    np.testing.assert_array_equal(batch.rewards, windows.rewards[:, 0])
    # the next state is the window's last: [episode, t + length]
    np.testing.assert_array_equal(batch.next_states[:, 1], batch.states[:, 1] + windows.lengths)
    np.testing.assert_array_equal(batch.next_states[:, 0], batch.states[:, 0])


def test_frame_replay_windows_do_not_cross_into_an_episode_that_starts_without_an_end_flag():
    """An episode cut short (a run stopped mid-episode, then a reset) has no end flag: the window must
    stop before the next episode's first transition, whose frames come from another episode."""
    rng = np.random.default_rng(0)
    rb = FrameReplay(capacity=40, frame_shape=(84, 84), stack=4, seed=0)
    obs_by_ep = []
    for ep, (length, end_flag) in enumerate([(7, False), (9, True)]):
        frames = rng.integers(0, 256, size=(length + 4, 84, 84), dtype=np.uint8)
        obs = [frames[t:t + 4] for t in range(length + 1)]
        obs_by_ep.append(obs)
        rb.end_episode()
        for t in range(length):
            rb.add(obs[t], t % 18, float(ep * 10 + t), obs[t + 1], end_flag and t == length - 1, False, t == 0)
    windows, last = rb._windows(np.arange(16), 5)
    assert list(windows.lengths[:7]) == [5, 5, 5, 4, 3, 2, 1]       # episode 0 (7 steps, no end flag)
    assert list(windows.lengths[7:]) == [5, 5, 5, 5, 5, 4, 3, 2, 1]
    batch = rb.take(np.arange(16), last)
    for t in range(7):                                               # next state = obs[t + length], exact frames
        np.testing.assert_array_equal(batch.next_states[t], obs_by_ep[0][t + windows.lengths[t]])
    np.testing.assert_array_equal(batch.next_states[7], obs_by_ep[1][5])
    assert batch.terminated[15] and batch.terminated[14] and not batch.terminated[7]


@pytest.mark.parametrize("double_dqn", [False, True])
def test_n_step_targets_equal_the_discounted_clipped_sum_plus_the_discounted_bootstrap(double_dqn):
    lrn = ComperLearner(config_from_dict(ComperConfig, {"variant": "dqn", "double_dqn": double_dqn, "seed": 2}),
                        obs_shape=(3,), n_actions=4)
    with torch.no_grad():
        for p in lrn.q_target.parameters():
            p.add_(0.1 * torch.randn_like(p))
    rng = np.random.default_rng(1)
    k, n, gamma = 6, 4, 0.99
    rewards = rng.integers(-5, 6, size=(k, n)).astype(np.float32)
    lengths = np.array([1, 2, 3, 4, 4, 2])
    for i, m in enumerate(lengths):
        rewards[i, m:] = 0.0
    term = np.array([False, True, False, False, True, False])
    ns = rng.normal(size=(k, 3)).astype(np.float32)
    batch = Transitions(states=rng.normal(size=(k, 3)).astype(np.float32), actions=rng.integers(4, size=k),
                        rewards=rewards[:, 0].copy(), next_states=ns, terminated=term, truncated=np.zeros(k, bool))
    with torch.no_grad():
        q_next = lrn.q_target(torch.as_tensor(ns)).numpy()
        pick = lrn.q(torch.as_tensor(ns)).argmax(1).numpy() if double_dqn else q_next.argmax(1)
    want = np.array([sum(gamma ** j * np.clip(rewards[i, j], -1, 1) for j in range(lengths[i]))
                     + (0.0 if term[i] else gamma ** lengths[i] * q_next[i, pick[i]]) for i in range(k)])
    y = lrn.targets(batch, n_step=NStepRewards(rewards, lengths)).numpy()
    np.testing.assert_allclose(y, want, rtol=1e-5, atol=1e-5)
    # windows of one step are the one-step target
    one = NStepRewards(rewards[:, :1].copy(), np.ones(k, np.int64))
    np.testing.assert_allclose(lrn.targets(batch, n_step=one).numpy(), lrn.targets(batch).numpy(), rtol=1e-6)
    assert ComperConfig().n_step == 1


def _labelled_rows(lengths_and_ends, seed=0):
    """One-step rows of consecutive episodes as comper_node labels them: label = max_a Q(s', a) stand-in
    (a number naming the step), 0 when terminated. Returns a list of episodes, each a list of rows."""
    rng = np.random.default_rng(seed)
    episodes, step = [], 0
    for e, (length, end) in enumerate(lengths_and_ends):
        rows = []
        for t in range(length):
            last = t == length - 1
            term, trunc = last and end == "terminated", last and end == "truncated"
            rows.append(Row(np.array([e, t], np.float32), int(rng.integers(3)), float(rng.integers(-3, 4)),
                            np.array([e, t + 1], np.float32), term, trunc, step, 0.0 if term else 100.0 + step))
            step += 1
        episodes.append(rows)
    return episodes


@pytest.mark.parametrize("clip", ["sign", "none"])
def test_comper_windows_equal_the_episodes_discounted_clipped_sums_and_drop_only_truncated_cuts(clip):
    n, gamma = 4, 0.9
    eps = _labelled_rows([(7, "terminated"), (9, "truncated"), (2, "terminated"), (6, "stopped"), (3, "truncated")])
    f = np.sign if clip == "sign" else (lambda r: r)
    builder = NStepWindows(n, gamma, f)
    rng = np.random.default_rng(5)
    got = []
    for rows in eps:
        builder.reset()                                   # comper_node: a new episode
        i = 0
        while i < len(rows):                              # stored in flushes of any size
            k = int(rng.integers(1, 5))
            got += builder.push(rows[i:i + k])
            i += k
    builder.reset()                                       # the run ends mid-episode ("stopped")
    want, dropped = [], 0
    for rows in eps:
        for i in range(len(rows)):
            w = rows[i:i + n]
            ends = [j for j, r in enumerate(w) if r.terminated]
            if ends:
                w = w[:ends[0] + 1]                       # a termination ends the window: kept, any length
            elif len(w) < n or any(r.truncated for r in w[:-1]):
                dropped += 1                              # cut short by a truncation or the run's stop
                continue
            want.append((w[0].step, sum(gamma ** j * f(r.reward) for j, r in enumerate(w)), w[-1]))
    assert [g.step for g in got] == [s for s, _, _ in want]
    for g, (_, ret, last) in zip(got, want):
        assert g.reward == pytest.approx(ret, abs=1e-12)
        np.testing.assert_array_equal(g.next_state, last.next_state)
        assert (g.terminated, g.truncated, g.label) == (last.terminated, last.truncated, last.label)
    assert builder.dropped == dropped == (3 + 0 + 0 + 3 + 3)
    # the window that ends exactly at a truncation is kept, with its bootstrap (not terminated)
    assert any(g.truncated and not g.terminated for g in got)
    with pytest.raises(ValueError, match="no value label"):
        builder.push([Row(np.zeros(2), 0, 1.0, np.zeros(2), False, False, 99, None)])


@pytest.mark.parametrize("variant", ["comper", "comper_f"])
def test_comper_targets_on_stored_windows_bootstrap_n_steps_on_without_clipping_the_window_return(variant):
    n, gamma = 5, 0.99
    lrn = ComperLearner(config_from_dict(ComperConfig, {"variant": variant, "n_step": n, "seed": 3,
                                                        "reward_clip": "sign"}), obs_shape=(3,), n_actions=4)
    rng = np.random.default_rng(2)
    k = 6
    ret = np.array([2.5, -3.9, 0.0, 4.1, -0.5, 1.0], np.float32)          # window returns, already clipped per step
    term = np.array([False, True, False, False, True, False])
    ns = rng.normal(size=(k, 3)).astype(np.float32)
    batch = Transitions(states=rng.normal(size=(k, 3)).astype(np.float32), actions=rng.integers(4, size=k),
                        rewards=ret, next_states=ns, terminated=term, truncated=np.zeros(k, bool))
    qt = rng.normal(size=k).astype(np.float32)
    if variant == "comper":
        boot = qt
        y = lrn.targets(batch, qt).numpy()
    else:
        with torch.no_grad():
            boot = lrn.q_target(torch.as_tensor(ns)).max(1).values.numpy()
        y = lrn.targets(batch).numpy()
    want = ret + gamma ** n * (1 - term) * boot
    np.testing.assert_allclose(y, want, rtol=1e-5, atol=1e-5)
    with pytest.raises(ValueError, match="no replay windows"):
        lrn.targets(batch, qt, n_step=NStepRewards(ret[:, None], np.ones(k, np.int64)))

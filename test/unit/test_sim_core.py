"""Unit tests of the simulation bridge core on vector tasks (MuJoCo, classic control): stepping,
episode-end rules, validation (every refused request leaves the state unchanged), determinism."""
import numpy as np
import pytest

from comper_msgs_py.params import ConfigError, config_from_dict
from comper_sim.core import EnvError, SimBridge, SimConfig, SimError


def bridge(env_id="Hopper-v4", **kw) -> SimBridge:
    return SimBridge(SimConfig(env_id=env_id, **kw))


def snapshot(b: SimBridge):
    """Everything a refused request must not change, the simulator's own state included."""
    inner = b.env.env.unwrapped
    sim = (inner.data.qpos.copy(), inner.data.qvel.copy()) if hasattr(inner, "data") else (np.array(inner.state).copy(),)
    return (None if b.observation is None else b.observation.copy(), b.episode_id, b.episode_step,
            b.episode_frames, b.episode_return, b.total_steps, b.total_frames, b.needs_reset, sim)


def assert_same(a, b):
    assert len(a) == len(b)
    for x, y in zip(a, b):
        if isinstance(x, tuple):
            assert_same(x, y)
        elif isinstance(x, np.ndarray):
            np.testing.assert_array_equal(x, y)
        else:
            assert x == y


def test_hopper_reset_and_step_raw_float32():
    b = bridge()
    obs, ep = b.reset()
    assert obs.dtype == np.float32 and obs.shape == (11,) and ep == 0
    r = b.step(np.zeros(3, np.float32))
    assert r.observation.dtype == np.float32 and r.observation.shape == (11,)
    assert isinstance(r.reward, float) and r.episode_step == 1 and r.frames == 1
    assert r.terminated is False and r.truncated is False and r.episode_over is False
    info = b.info()
    assert info.discrete is False and info.action_shape == (3,) and info.max_episode_steps == 1000
    assert info.frame_skip == 1 and info.observation_dtype == np.float32
    np.testing.assert_array_equal(info.action_low, -np.ones(3, np.float32))


@pytest.mark.parametrize("env_id,obs_dim,act_dim", [("Pendulum-v1", 3, 1), ("MountainCarContinuous-v0", 2, 1),
                                                    ("Hopper-v5", 11, 3)])
def test_other_tasks(env_id, obs_dim, act_dim):
    b = bridge(env_id)
    obs, _ = b.reset()
    assert obs.shape == (obs_dim,) and obs.dtype == np.float32
    res = b.step_many(np.zeros((5, act_dim), np.float32))
    assert res.transitions.states.shape == (5, obs_dim) and res.transitions.actions.shape == (5, act_dim)


def test_unknown_env_id_is_a_clear_error():
    with pytest.raises(EnvError, match="NoSuchEnv-v0"):
        bridge("NoSuchEnv-v0")


def test_config_refuses_bad_values():
    with pytest.raises(ConfigError, match="episode_end"):
        config_from_dict(SimConfig, {"episode_end": "sometimes"})
    with pytest.raises(ConfigError, match="action_out_of_range"):
        config_from_dict(SimConfig, {"action_out_of_range": "wrap"})
    with pytest.raises(ConfigError, match="frame_stack"):
        config_from_dict(SimConfig, {"frame_stack": 0})


# --- episode ends -------------------------------------------------------------------------------
def run_until_over(b, action, limit):
    for _ in range(limit):
        r = b.step(action)
        if r.episode_over:
            return r
    raise AssertionError(f"episode did not end within {limit} steps")


def test_time_limit_override_and_standard_rule():
    b = bridge("Pendulum-v1", max_episode_steps=7)
    b.reset()
    r = run_until_over(b, np.zeros(1, np.float32), 10)
    assert r.episode_step == 7 and r.truncated and not r.terminated
    assert r.episode is not None and r.episode.length == 7 and r.episode.frames == 7 and r.episode.truncated
    with pytest.raises(SimError, match="call reset"):
        b.step(np.zeros(1, np.float32))
    _, ep = b.reset()
    assert ep == 1


def test_termination_only_ignores_the_time_limit_but_reports_truncated():
    b = bridge("Pendulum-v1", max_episode_steps=5, episode_end="termination_only")
    b.reset()
    flags = [b.step(np.zeros(1, np.float32)) for _ in range(8)]
    assert [f.truncated for f in flags] == [False] * 4 + [True] * 4   # reported as the env gives it
    assert not any(f.episode_over for f in flags) and b.episode_step == 8


def hopper_falls(b):
    """Hopper with a constant strong action falls within a few dozen steps."""
    b.reset(seed=3)
    a = np.array([1.0, -1.0, 1.0], np.float32)
    for _ in range(200):
        r = b.step(a)
        if r.terminated:
            return r
    raise AssertionError("Hopper did not fall")


def test_standard_rule_ends_on_terminated():
    b = bridge(max_episode_steps=300)
    r = hopper_falls(b)
    assert r.episode_over and r.terminated and not r.truncated and b.needs_reset
    assert r.episode.terminated and not r.episode.truncated


def test_truncation_only_continues_after_terminated():
    b = bridge(max_episode_steps=300, episode_end="truncation_only")
    r = hopper_falls(b)
    assert r.terminated and not r.episode_over and not b.needs_reset
    r = run_until_over(b, np.zeros(3, np.float32), 300)
    assert r.truncated and r.episode_step == 300


# --- step_many -----------------------------------------------------------------------------------
def test_step_many_autoreset_transitions_are_consistent():
    b = bridge("Pendulum-v1", max_episode_steps=10)
    b.reset()
    acts = np.random.default_rng(0).uniform(-2, 2, (35, 1)).astype(np.float32)
    res = b.step_many(acts, autoreset=True)
    t = res.transitions.validate()
    assert len(t) == 35 and res.episodes_ended == 3 and len(res.episodes) == 3
    np.testing.assert_array_equal(t.actions, acts)
    np.testing.assert_array_equal(t.steps, np.arange(35, dtype=np.uint64))
    np.testing.assert_array_equal(t.episode_ids, np.repeat(np.arange(4, dtype=np.uint64), [10, 10, 10, 5]))
    ends = np.flatnonzero(t.truncated)
    np.testing.assert_array_equal(ends, [9, 19, 29])
    for i in range(34):   # the chain s' -> s holds except across an episode end
        if i not in ends:
            np.testing.assert_array_equal(t.next_states[i], t.states[i + 1])
    np.testing.assert_array_equal(res.observation, b.observation)
    assert b.episode_id == 3 and b.episode_step == 5 and b.total_steps == 35
    assert [e.global_step for e in res.episodes] == [10, 20, 30]


def test_step_many_without_autoreset_stops_at_the_end():
    b = bridge("Pendulum-v1", max_episode_steps=10)
    b.reset()
    res = b.step_many(np.zeros((25, 1), np.float32), autoreset=False)
    assert len(res.transitions) == 10 and res.episodes_ended == 1 and b.needs_reset
    assert res.transitions.truncated[-1]
    with pytest.raises(SimError, match="call reset"):
        b.step_many(np.zeros((2, 1), np.float32), autoreset=True)


# --- validation: refused, state unchanged ------------------------------------------------------
BAD_CONTINUOUS = [
    ("shape", np.zeros(2, np.float32), "shape"),
    ("shape2d", np.zeros((1, 3), np.float32), "shape"),
    ("nan", np.array([0, np.nan, 0], np.float32), "NaN or Inf"),
    ("inf", np.array([np.inf, 0, 0], np.float32), "NaN or Inf"),
    ("range", np.array([0, 1.5, 0], np.float32), "outside the action bounds"),
    ("text", "up", "numeric"),
    ("ragged", [[1, 2], [3]], "array of numbers|numeric"),
]
BAD_CONTINUOUS_BATCH = [
    ("shape", np.zeros((4, 2), np.float32), "shape"),
    ("flat", np.zeros(4, np.float32), "shape"),
    ("empty", np.zeros((0, 3), np.float32), "empty"),
    ("nan-row", np.vstack([np.zeros((3, 3)), [[0, 0, np.nan]]]).astype(np.float32), "row 3"),
    ("range-row", np.vstack([np.zeros((2, 3)), [[0, -1.01, 0]]]).astype(np.float32), "row 2"),
]


@pytest.mark.parametrize("name,action,match", BAD_CONTINUOUS, ids=[c[0] for c in BAD_CONTINUOUS])
def test_bad_step_is_refused_and_changes_nothing(name, action, match):
    b, twin = bridge(), bridge()
    b.reset(), twin.reset()
    a = np.full(3, 0.3, np.float32)
    b.step(a), twin.step(a)
    before = snapshot(b)
    with pytest.raises(SimError, match=match):
        b.step(action)
    assert_same(snapshot(b), before)
    np.testing.assert_array_equal(b.step(a).observation, twin.step(a).observation)


@pytest.mark.parametrize("name,actions,match", BAD_CONTINUOUS_BATCH, ids=[c[0] for c in BAD_CONTINUOUS_BATCH])
def test_bad_step_many_is_refused_and_changes_nothing(name, actions, match):
    b, twin = bridge(), bridge()
    b.reset(), twin.reset()
    before = snapshot(b)
    with pytest.raises(SimError, match=match):
        b.step_many(actions)
    assert_same(snapshot(b), before)
    good = np.full((3, 3), -0.2, np.float32)
    np.testing.assert_array_equal(b.step_many(good).transitions.next_states,
                                  twin.step_many(good).transitions.next_states)


def test_step_before_reset_is_refused():
    b = bridge()
    with pytest.raises(SimError, match="reset first"):
        b.step(np.zeros(3, np.float32))
    with pytest.raises(SimError, match="reset first"):
        b.step_many(np.zeros((2, 3), np.float32))
    assert b.episode_id == -1 and b.total_steps == 0


def test_clip_mode_clips_and_records_the_applied_action():
    b, twin = bridge(action_out_of_range="clip"), bridge()
    b.reset(), twin.reset()
    res = b.step_many(np.array([[5, -5, 0.5]], np.float32))
    np.testing.assert_array_equal(res.transitions.actions, [[1, -1, 0.5]])
    np.testing.assert_array_equal(res.observation, twin.step(np.array([1, -1, 0.5], np.float32)).observation)
    with pytest.raises(SimError, match="NaN"):     # clip never hides non-finite values
        b.step(np.array([np.nan, 0, 0], np.float32))


BAD_DISCRETE = [("high", 2, "outside \\[0, 2\\)"), ("negative", -1, "outside"),
                ("fraction", 0.5, "whole number"), ("nan", np.nan, "NaN"), ("two", [0, 1], "one index"),
                ("bool", np.array(True), "numeric")]


@pytest.mark.parametrize("name,action,match", BAD_DISCRETE, ids=[c[0] for c in BAD_DISCRETE])
def test_discrete_bad_actions_refused(name, action, match):
    b = bridge("CartPole-v1")
    b.reset()
    before = snapshot(b)
    with pytest.raises(SimError, match=match):
        b.step(action)
    assert_same(snapshot(b), before)
    assert b.step(np.float32(1)).episode_step == 1


# --- determinism ---------------------------------------------------------------------------------
def rollout(b, seed=None, n=60):
    obs, _ = b.reset(seed)
    acts = np.random.default_rng(1).uniform(-1, 1, (n, 3)).astype(np.float32)
    res = b.step_many(acts)
    return np.concatenate([obs[None], res.transitions.next_states]), res.transitions.rewards


def test_deterministic_given_seed():
    o1, r1 = rollout(bridge(seed=5))
    o2, r2 = rollout(bridge(seed=5))
    o3, _ = rollout(bridge(seed=6))
    np.testing.assert_array_equal(o1, o2)
    np.testing.assert_array_equal(r1, r2)
    assert not np.array_equal(o1, o3)
    b = bridge(seed=6)
    rollout(b)
    o4, _ = rollout(b, seed=5)        # an explicit reseed reproduces the seed-5 run
    np.testing.assert_array_equal(o1, o4)


def test_play_episode_runs_one_whole_episode_and_repeats_with_its_seed():
    b = SimBridge(SimConfig(env_id="Pendulum-v1", seed=0, max_episode_steps=25))
    seen = []

    def policy(obs):
        seen.append(obs)
        return np.zeros(1, np.float32)
    ret, n, last = b.play_episode(policy, seed=5)
    assert n == 25 == len(seen) and last.episode_over and last.truncated and not last.terminated
    assert ret < 0                                   # Pendulum rewards are costs
    again = b.play_episode(lambda obs: np.zeros(1, np.float32), seed=5)
    assert again[:2] == (ret, n)                     # same seed, same policy: same episode
    b.close()

"""Unit tests of the ALE protocol (method.md 5, Machado et al. 2018) in the simulation bridge core:
18 actions, frame skip 5 counted in frames, sticky actions 0.25 configured inside ALE, colour
averaging + luminance + 84x84 area resize as uint8, frame stacks, game over ends the episode,
no life-loss signal, refused requests change nothing, determinism."""
import numpy as np
import pytest

from comper_sim.core import AreaResize, SimBridge, SimConfig, SimError, area_resize_matrix

FREEWAY = "ALE/Freeway-v5"


def bridge(env_id=FREEWAY, **kw) -> SimBridge:
    return SimBridge(SimConfig(env_id=env_id, **kw))


@pytest.fixture(scope="module")
def freeway():
    b = bridge()
    yield b
    b.close()


def test_protocol_is_configured_inside_ale(freeway):
    env = freeway.env
    ale = env.ale
    assert ale.getFloat("repeat_action_probability") == pytest.approx(0.25)
    assert env.ale_env._frameskip == 1          # the skip loop is ours, one ale.act per frame
    assert env.frame_skip == 5
    assert env.num_actions == 18 and len(ale.getLegalActionSet()) == 18
    assert len(ale.getMinimalActionSet()) < 18  # Freeway's minimal set is smaller: the full set is in use
    info = freeway.info()
    assert info.discrete and info.num_actions == 18 and info.frame_skip == 5
    assert info.observation_shape == (84, 84) and info.observation_dtype == np.uint8
    assert info.spec["repeat_action_probability"] == pytest.approx(0.25)
    assert info.spec["life_loss_signal"] is False and info.spec["colour_averaging"] is True


def test_single_frame_shape_dtype_and_frame_counting(freeway):
    obs, _ = freeway.reset(seed=0)
    assert obs.shape == (84, 84) and obs.dtype == np.uint8
    total0 = freeway.total_frames
    for i in range(1, 6):
        r = freeway.step(i % 18)
        assert r.observation.shape == (84, 84) and r.observation.dtype == np.uint8
        assert r.frames == 5 * i and r.episode_step == i
        assert freeway.env.ale.getEpisodeFrameNumber() == 5 * i   # the emulator agrees
    res = freeway.step_many(np.arange(10, dtype=np.float32) % 18)
    assert freeway.episode_frames == 75 and freeway.total_frames - total0 == 75
    assert res.transitions.states.dtype == np.uint8 and res.transitions.states.shape == (10, 84, 84)
    assert res.transitions.actions.shape == (10,)


def test_frame_stack_of_four():
    b = bridge(frame_stack=4)
    obs, _ = b.reset(seed=1)
    assert obs.shape == (4, 84, 84) and obs.dtype == np.uint8
    assert all(np.array_equal(obs[0], obs[k]) for k in range(4))      # filled with the first frame
    prev = obs
    for a in (1, 2, 3):
        o = b.step(a).observation
        np.testing.assert_array_equal(o[:-1], prev[1:])                # oldest first, shifts by one
        prev = o
    res = b.step_many(np.full(6, 2.0, np.float32))
    assert res.transitions.next_states.shape == (6, 4, 84, 84)
    assert b.info().observation_shape == (4, 84, 84)


def test_preprocessing_none_gives_raw_luminance():
    b = bridge(preprocessing="none")
    obs, _ = b.reset(seed=0)
    assert obs.shape == (210, 160) and obs.dtype == np.uint8
    np.testing.assert_array_equal(obs, b.env.ale.getScreenGrayscale())


def _skip_by_hand(b: SimBridge, action: int) -> list[np.ndarray]:
    """The 5 luminance screens of one frame skip, played on the bridge's ALE directly."""
    ale, act = b.env.ale, b.env._action_set[action]
    frames = []
    for _ in range(5):
        ale.act(act)
        frames.append(ale.getScreenGrayscale().astype(np.float64))
    return frames


def test_observation_is_the_resized_average_of_the_last_two_frames():
    """Replay the same seeded step by hand (sticky draws come from ALE's seeded RNG)."""
    a, b = bridge(), bridge()
    a.reset(seed=7), b.reset(seed=7)
    for action in (3, 3, 4):
        frames = _skip_by_hand(b, action)
        avg = (frames[-1] + frames[-2]) / 2
        expected = np.rint(area_resize_matrix(210, 84) @ avg @ area_resize_matrix(160, 84).T)
        got = a.step(action).observation.astype(np.float64)
        assert np.abs(got - expected).max() <= 1     # float32 vs float64 rounding at .5 only
        assert np.mean(got != expected) < 0.01


def test_frame_pooling_max_is_the_resized_maximum_of_the_last_two_frames():
    """The DQN baseline's Table 35 setting, replayed by hand like the average above."""
    a, b = bridge(frame_pooling="max"), bridge()
    assert a.info().spec["frame_pooling"] == "max" and a.info().spec["colour_averaging"] is False
    assert b.info().spec["frame_pooling"] == "average"
    a.reset(seed=7), b.reset(seed=7)
    differs = 0
    for action in (3, 3, 4, 1, 1):
        frames = _skip_by_hand(b, action)
        pooled = np.maximum(frames[-1], frames[-2])
        expected = np.rint(area_resize_matrix(210, 84) @ pooled @ area_resize_matrix(160, 84).T)
        avg = np.rint(area_resize_matrix(210, 84) @ ((frames[-1] + frames[-2]) / 2) @ area_resize_matrix(160, 84).T)
        got = a.step(action).observation.astype(np.float64)
        assert np.abs(got - expected).max() <= 1 and np.mean(got != expected) < 0.01
        differs += int(np.any(expected != avg))
    assert differs >= 1                                # the two poolings are not the same observation
    a.close(), b.close()


def test_area_resize_weights():
    w = area_resize_matrix(210, 84)
    np.testing.assert_allclose(w.sum(axis=1), 1.0)
    np.testing.assert_allclose(w.sum(axis=0), 84 / 210)      # every input pixel counts equally
    x = np.random.default_rng(0).uniform(0, 255, (210, 160)).astype(np.float32)
    ref = w @ x @ area_resize_matrix(160, 84).T
    np.testing.assert_allclose(AreaResize((210, 160), (84, 84))(x), ref, rtol=1e-5, atol=1e-3)
    const = np.full((210, 160), 77, np.float32)
    np.testing.assert_allclose(AreaResize((210, 160), (84, 84))(const), 77, atol=1e-3)


def test_game_over_ends_the_episode_even_under_truncation_only():
    b = bridge(episode_end="truncation_only", frame_skip=20)   # Freeway ends after ~8,200 frames
    b.reset(seed=0)
    for _ in range(1000):
        r = b.step(0)
        if r.episode_over:
            break
    assert r.episode_over and r.terminated and not r.truncated and b.needs_reset
    assert r.episode.frames == r.frames and 8000 < r.frames < 8400
    with pytest.raises(SimError, match="terminated"):
        b.step(0)


def test_frame_cap_truncates_and_counts_skipped_frames():
    b = bridge(max_episode_frames=52)
    b.reset(seed=0)
    res = b.step_many(np.zeros(20, np.float32), autoreset=False)
    assert len(res.transitions) == 11 and res.transitions.truncated[-1] and not res.transitions.terminated.any()
    assert res.episodes[0].frames == 52 and res.episodes[0].length == 11   # the last step stopped at the cap


def test_no_life_loss_signal():
    b = bridge("ALE/Breakout-v5")
    b.reset(seed=0)
    lives = b.env.ale.lives()
    rng = np.random.default_rng(0)
    for _ in range(3000):
        r = b.step(int(rng.integers(18)))
        if b.env.ale.lives() < lives:
            break
    assert b.env.ale.lives() < lives, "no life lost in 3000 random steps"
    assert not r.terminated and not r.episode_over           # losing a life is not an episode end


BAD = [("index18", 18, "outside \\[0, 18\\)"), ("negative", -1, "outside"), ("fraction", 2.5, "whole number"),
       ("nan", np.float32("nan"), "NaN"), ("inf", np.inf, "NaN or Inf"), ("shape", np.zeros(2), "one index")]


@pytest.mark.parametrize("name,action,match", BAD, ids=[c[0] for c in BAD])
def test_bad_actions_refused_state_unchanged(name, action, match):
    b, twin = bridge(), bridge()
    b.reset(seed=3), twin.reset(seed=3)
    b.step(1), twin.step(1)
    ram, obs, frames = b.env.ale.getRAM().copy(), b.observation.copy(), b.total_frames
    with pytest.raises(SimError, match=match):
        b.step(action)
    with pytest.raises(SimError, match="row 2" if np.ndim(action) == 0 else "outside"):
        b.step_many(np.array([1, 2, action if np.ndim(action) == 0 else 99], dtype=np.float64))
    np.testing.assert_array_equal(b.env.ale.getRAM(), ram)
    np.testing.assert_array_equal(b.observation, obs)
    assert b.total_frames == frames and b.episode_step == 1
    for a in (5, 6, 7):   # the sticky-action RNG was not consumed either
        np.testing.assert_array_equal(b.step(a).observation, twin.step(a).observation)


def test_deterministic_given_seed():
    acts = np.random.default_rng(0).integers(0, 18, 40).astype(np.float32)
    runs = []
    for seed in (11, 11, 12):
        b = bridge(seed=seed)
        b.reset()
        t = b.step_many(acts).transitions
        runs.append((t.next_states, t.rewards))
        b.close()
    np.testing.assert_array_equal(runs[0][0], runs[1][0])
    np.testing.assert_array_equal(runs[0][1], runs[1][1])
    # another seed changes the sticky draws: some frame differs (Freeway's cars are the same)
    b1, b2 = bridge(seed=11), bridge(seed=12)
    b1.reset(), b2.reset()
    ram1 = [b1.step(int(a)) and b1.env.ale.getRAM().copy() for a in acts]
    ram2 = [b2.step(int(a)) and b2.env.ale.getRAM().copy() for a in acts]
    assert any(not np.array_equal(x, y) for x, y in zip(ram1, ram2))

"""The replay buffers' contents in checkpoints (core/replay.py state_arrays / load_state_arrays, saved with
core/checkpoint.save_arrays): a buffer rebuilt from them draws exactly what the original draws next."""
import numpy as np
import pytest

from comper_agent.core.checkpoint import load_arrays, save_arrays
from comper_agent.core.replay import FrameReplay, ReplayBuffer
from comper_msgs_py.arrays import Transitions


def _fill_vector(rb, n, seed=0):
    rng = np.random.default_rng(seed)
    rb.add(Transitions(states=rng.normal(size=(n, 3)).astype(np.float32),
                       actions=rng.uniform(-1, 1, size=(n, 2)).astype(np.float32),
                       rewards=rng.normal(size=n).astype(np.float32),
                       next_states=rng.normal(size=(n, 3)).astype(np.float32),
                       terminated=rng.random(n) < 0.1, truncated=rng.random(n) < 0.05))


def _fill_frames(rb, episodes, seed=0):
    rng = np.random.default_rng(seed)
    for length in episodes:
        frames = rng.integers(0, 256, size=(length + 4, 84, 84), dtype=np.uint8)
        rb.end_episode()
        for t in range(length):
            rb.add(frames[t:t + 4], t % 18, float(t), frames[t + 1:t + 5], t == length - 1, False, t == 0)


def _same(a: Transitions, b: Transitions):
    for f in ("states", "actions", "rewards", "next_states", "terminated", "truncated"):
        assert np.array_equal(getattr(a, f), getattr(b, f)), f


@pytest.mark.parametrize("n", [10, 50])          # part filled; wrapped around (capacity 32)
def test_vector_replay_round_trip_draws_the_same(tmp_path, n):
    rb = ReplayBuffer(32, (3,), (2,), seed=1)
    _fill_vector(rb, n)
    rb.sample(5)                                  # the random stream has moved
    save_arrays(tmp_path / "r.npz", rb.state_arrays())
    back = ReplayBuffer(32, (3,), (2,), seed=99)
    back.load_state_arrays(load_arrays(tmp_path / "r.npz"))
    assert (back.pos, back.size) == (rb.pos, rb.size)
    for _ in range(3):
        _same(back.sample(8), rb.sample(8))
    windows_a, windows_b = back.sample(6, n_step=3), rb.sample(6, n_step=3)
    _same(windows_a[0], windows_b[0])
    assert np.array_equal(windows_a[1].rewards, windows_b[1].rewards)


def test_frame_replay_round_trip_keeps_only_the_live_frames_and_draws_the_same(tmp_path):
    rb = FrameReplay(capacity=40, frame_shape=(84, 84), stack=4, seed=0)
    _fill_frames(rb, [60, 50])                    # 110 transitions into 40 slots, 116 frames into 104
    saved = rb.state_arrays()
    assert saved["frames"].shape == (rb.n_frames, 84, 84)    # every frame slot written by now
    small = FrameReplay(capacity=40, frame_shape=(84, 84), stack=4, seed=0)
    _fill_frames(small, [5])
    assert small.state_arrays()["frames"].shape == (4 + 5, 84, 84)   # only the frames written
    save_arrays(tmp_path / "f.npz", saved)
    back = FrameReplay(capacity=40, frame_shape=(84, 84), stack=4, seed=5)
    back.load_state_arrays(load_arrays(tmp_path / "f.npz"))
    assert back.frames_written == rb.frames_written and back._last_ns is None
    for _ in range(3):
        _same(back.sample(8), rb.sample(8))


def test_a_replay_that_does_not_fit_is_refused_and_the_buffer_untouched():
    rb = ReplayBuffer(32, (3,), (2,), seed=1)
    _fill_vector(rb, 10)
    saved = rb.state_arrays()
    other = ReplayBuffer(64, (3,), (2,), seed=1)
    with pytest.raises(ValueError, match="does not fit"):
        other.load_state_arrays(saved)
    assert len(other) == 0 and not other.states.any()
    bad = {**saved, "rewards": saved["rewards"][:-1]}
    with pytest.raises(ValueError, match="inconsistent"):
        ReplayBuffer(32, (3,), (2,)).load_state_arrays(bad)
    with pytest.raises(ValueError, match="not a saved replay"):
        ReplayBuffer(32, (3,), (2,)).load_state_arrays({"states": saved["states"]})
    frames = FrameReplay(capacity=40, frame_shape=(84, 84), stack=4, seed=0)
    _fill_frames(frames, [6])
    fsaved = frames.state_arrays()
    fresh = FrameReplay(capacity=40, frame_shape=(84, 84), stack=4, seed=0)
    with pytest.raises(ValueError, match="frames do not match"):
        fresh.load_state_arrays({**fsaved, "frames": fsaved["frames"][:-1]})
    assert len(fresh) == 0 and fresh.frames_written == 0 and not fresh.s_ids.any()
    with pytest.raises(ValueError, match="does not fit"):
        ReplayBuffer(40, (3,), (2,)).load_state_arrays(fsaved)

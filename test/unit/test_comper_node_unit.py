"""comper_node pieces that need no running ROS graph: the protocol summary (last-10 / terciles),
the DQN baseline's frame-deduplicating replay (exact reconstruction across episodes, ring overwrite) and
the rows waiting for their value label (PendingRows)."""
import numpy as np
import pytest

from comper_agent.core.protocol import protocol_summary
from comper_agent.core.replay import FrameReplay


def test_protocol_summary_last_ten_and_terciles_of_the_frame_budget():
    r = list(range(30))                     # 30 episodes of 100 frames: terciles end at 1,000, 2,000, 3,000
    s = protocol_summary(r, np.cumsum([100] * 30), 3000)
    assert s["episodes"] == 30 and s["last_k"] == 10 and s["last_mean"] == pytest.approx(np.mean(r[-10:]))
    assert [t["end_episode"] for t in s["terciles"]] == [10, 20, 30]
    assert [t["mean"] for t in s["terciles"]] == pytest.approx([7.0, 17.0, 27.0])
    assert all(t["n"] == 5 for t in s["terciles"])


def test_terciles_follow_frames_not_episode_counts():
    """Section 5.3: checkpoints at each third of the total frames. An agent whose episodes get longer
    ends fewer episodes in the later thirds; counting episodes would move the checkpoints."""
    lengths = [50] * 20 + [200] * 10        # 1,000 frames in 20 episodes, then 2,000 in 10
    s = protocol_summary(list(range(30)), np.cumsum(lengths), 3000)
    assert [t["end_episode"] for t in s["terciles"]] == [20, 25, 30]
    assert [t["mean"] for t in s["terciles"]] == pytest.approx([17.0, 22.0, 27.0])


def test_protocol_summary_few_episodes_uses_three():
    r = [1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0]   # < 25 episodes: last 3, terciles of the last 3
    s = protocol_summary(r, np.cumsum([10] * 7), 70)
    assert s["last_k"] == 3 and s["last_mean"] == pytest.approx(6.0) and s["tercile_k"] == 3
    assert [t["end_episode"] for t in s["terciles"]] == [2, 4, 7]
    assert [t["mean"] for t in s["terciles"]] == pytest.approx([1.5, 3.0, 6.0])
    assert np.isnan(protocol_summary([], [])["last_mean"])


def _episode(rng, length, stack):
    """Observations as the sim stacks them: oldest first, filled with the first frame at reset."""
    frames = rng.integers(0, 256, size=(length + 1, 84, 84), dtype=np.uint8)
    obs = []
    for t in range(length + 1):
        idx = [max(0, t - k) for k in range(stack - 1, -1, -1)]
        obs.append(frames[idx] if stack > 1 else frames[t])
    return obs


@pytest.mark.parametrize("stack", [1, 4])
def test_frame_replay_reconstructs_transitions_exactly(stack):
    rng = np.random.default_rng(0)
    rb = FrameReplay(capacity=50, frame_shape=(84, 84), stack=stack, seed=0, frame_margin=16)
    truth = []
    for ep_len in (7, 30, 25):               # 62 transitions into capacity 50: the ring wraps
        obs = _episode(rng, ep_len, stack)
        rb.end_episode()
        for t in range(ep_len):
            rb.add(obs[t], t % 18, float(t), obs[t + 1], t == ep_len - 1, False, t == 0)
            truth.append((obs[t], obs[t + 1]))
    assert len(rb) == 50
    # slots hold the last 50 transitions; those whose frames survived the ring reconstruct exactly
    last = truth[-50:]
    valid = rb._valid(np.arange(50))
    assert valid.sum() >= 40
    for slot in np.flatnonzero(valid):
        k = (slot - rb.pos) % 50                 # age order: rb.pos is the oldest slot
        t = rb.take([slot])
        np.testing.assert_array_equal(t.states[0], last[k][0])
        np.testing.assert_array_equal(t.next_states[0], last[k][1])
    b = rb.sample(32)
    assert b.states.dtype == np.uint8 and b.states.shape == ((32, 84, 84) if stack == 1 else (32, stack, 84, 84))
    # each frame stored once: far less than two observations per transition
    assert rb.frames.shape[0] == 66


def test_pending_rows_store_only_the_labelled_prefix():
    """COMPER labels a step with max_a Q(s', a) computed to act at the next step: the newest row waits
    for its label, the rows before it can be stored, oldest first."""
    from comper_agent.core.memory_schedule import PendingRows, Row
    obs = np.zeros(4, np.float32)
    rows = PendingRows()
    assert rows.newest_unlabelled() is None and rows.labelled() == 0 and rows.take_labelled() == []
    for step in range(3):
        waiting = rows.newest_unlabelled()
        if waiting is not None:
            waiting.label = float(step)          # the next step's Q-values label the previous row
        rows.append(Row(obs, 0, 1.0, obs, False, False, step))
    assert len(rows) == 3 and rows.labelled() == 2
    taken = rows.take_labelled()
    assert [r.step for r in taken] == [0, 1] and [r.label for r in taken] == [1.0, 2.0]
    assert len(rows) == 1 and rows.newest_unlabelled().step == 2
    rows.newest_unlabelled().label = 0.0         # a terminal step is labelled 0 at once
    assert [r.step for r in rows.take_labelled()] == [2] and len(rows) == 0

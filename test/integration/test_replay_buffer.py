"""The memory service as a replay buffer for other learners, over real ROS 2 (memory_node in its own
process, no mocks): MemoryReplayBuffer (numpy in and out, default labels, near-duplicates collapse,
terminations and truncations kept apart, bad input refused before anything is sent), the
Stable-Baselines3 adapter's add/sample against what was added, and the examples/ TD3 script
training through a memory node in another process."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("stable_baselines3", reason="a test extra (requirements-extras.lock), installed by the set-up")
from gymnasium import spaces  # noqa: E402

from comper_memory.replay_buffer import DEFAULT_LABEL, MemoryReplayBuffer  # noqa: E402
from comper_memory.sb3 import CompactReplayBuffer  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]


def start_memory(launch, tag):
    name = f"mem_rb_{tag}_{os.getpid()}"
    launch("comper_memory", "memory_node", "--ros-args", "-r", f"__node:={name}", "-p", "stats_period_s:=0.0",
           name=name)
    return name


def rows(n, seed=0, obs=3, act=2):
    rng = np.random.default_rng(seed)
    return (rng.normal(size=(n, obs)), rng.uniform(-1, 1, (n, act)), rng.normal(size=n),
            rng.normal(size=(n, obs)), rng.random(n) < 0.3, rng.random(n) < 0.3)


def test_memory_replay_buffer_round_trip_labels_duplicates_and_bad_input(launch):
    name = start_memory(launch, "facade")
    with MemoryReplayBuffer(name, store_every=8) as buf:
        o, a, r, o2, term, trunc = rows(40)
        buf.extend(o, a, r, o2, term, trunc)
        buf.add(o[0], a[0], r[0], o2[0], term[0], trunc[0])    # the same transition again: one identity
        assert len(buf) == 40 and buf.added == 41
        b = buf.sample(40, seed=3)
        order = np.argsort(b["obs"][:, 0])
        ref = np.argsort(o[:, 0].astype(np.float32))
        np.testing.assert_array_equal(b["obs"][order], o[ref].astype(np.float32))
        np.testing.assert_array_equal(b["next_obs"][order], o2[ref].astype(np.float32))
        np.testing.assert_array_equal(b["terminated"][order], term[ref])
        np.testing.assert_array_equal(b["truncated"][order], trunc[ref])
        assert np.all(b["label"] == DEFAULT_LABEL)
        assert sorted(b["count"].tolist()) == [1] * 39 + [2]
        with pytest.raises(ValueError, match="NaN"):
            buf.extend(np.full((2, 3), np.nan), a[:2], r[:2], o2[:2], term[:2])
        assert len(buf) == 40                                    # nothing half-stored
        full = buf.sample(64, fill=True)                          # fewer identities than asked: repeats
        assert len(full["obs"]) == 64 and len(np.unique(full["identity_id"])) == 40
        with pytest.raises(Exception, match="exceeds"):
            buf.sample(64)
        buf.extend(o + 10, a, r, o2, term, trunc, label=np.arange(40))
        assert sorted(buf.sample(80)["label"].tolist()) == [0.0] * 40 + list(map(float, range(40)))


def test_sb3_adapter_stores_terminations_and_truncations_apart(launch):
    name = start_memory(launch, "sb3")
    obs_space = spaces.Box(-np.inf, np.inf, (3,), np.float32)
    act_space = spaces.Box(-1.0, 1.0, (2,), np.float32)
    rb = CompactReplayBuffer(1000, obs_space, act_space, "cpu", n_envs=2, memory_node=name)
    try:
        o, a, r, o2, _, _ = rows(20)
        done = np.array([True, False] * 10)
        for i in range(0, 20, 2):
            infos = [{"TimeLimit.truncated": i % 4 == 0}, {}]        # env 0 alternates truncation / termination
            rb.add(o[i:i + 2], o2[i:i + 2], a[i:i + 2], r[i:i + 2], done[i:i + 2], infos)
        assert rb.size() == 20 and rb.pos == 10
        s = rb.sample(20)
        assert s.observations.shape == (20, 3) and s.actions.shape == (20, 2) and s.dones.shape == (20, 1)
        got = {round(float(x), 5): float(d) for x, d in zip(s.observations[:, 0], s.dones[:, 0])}
        want = {round(float(np.float32(o[i, 0])), 5): float(done[i] and not (i % 2 == 0 and i % 4 == 0))
                for i in range(20)}
        assert got == want          # truncated episode ends are not terminations
        np.testing.assert_allclose(sorted(s.rewards[:, 0].tolist()), sorted(r.astype(np.float32).tolist()), rtol=1e-6)
    finally:
        rb.close()
    with pytest.raises(ValueError, match="optimize_memory_usage"):
        CompactReplayBuffer(10, obs_space, act_space, optimize_memory_usage=True, memory_node=name)


def test_sb3_td3_example_trains_through_a_memory_node_in_another_process(launch, tmp_path):
    name = start_memory(launch, "td3")
    out = tmp_path / "summary.json"
    proc = subprocess.run([sys.executable, str(ROOT / "examples" / "sb3_td3_through_memory.py"),
                           "--env-id", "InvertedPendulum-v4", "--total-steps", "300", "--learning-starts", "100",
                           "--memory-node", name, "--eval-episodes", "2", "--out", str(out)],
                          capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    summary = json.loads(out.read_text())
    m = summary["memory"]
    assert m["transitions_stored"] == 300 and 0 < m["identities"] <= 300
    assert m["reductions"] >= 200 and m["rate_samples"] >= 200 * 100     # one draw per gradient step
    assert len(summary["eval_returns"]) == 2

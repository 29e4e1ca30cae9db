"""The memory service as a replay buffer for other learners, over real ROS 2 (memory_node in its own
process, no mocks): MemoryReplayBuffer (numpy in and out, default labels, near-duplicates collapse,
terminations and truncations kept apart, bad input refused before anything is sent), every transition
added before a sample in its draw (bulk adds past reduce_batch, other clients' sets in TM, batched
stores and prefetched batches), seeded draws the same run after run, the Stable-Baselines3 adapter's
add/sample against what was added, and the examples/ TD3 script training through a memory node in
another process, twice with one seed to the same evaluation."""
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

from comper_memory import replay_buffer  # noqa: E402
from comper_memory.client import MemoryClient, MemoryServiceError  # noqa: E402
from comper_memory.replay_buffer import DEFAULT_LABEL, PENDING_IDENTITY, MemoryReplayBuffer  # noqa: E402
from comper_msgs_py.arrays import Transitions  # noqa: E402
from comper_memory.sb3 import CompactReplayBuffer  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]


def start_memory(launch, tag, *params):
    name = f"mem_rb_{tag}_{os.getpid()}"
    launch("comper_memory", "memory_node", "--ros-args", "-r", f"__node:={name}", "-p", "stats_period_s:=0.0",
           *[a for p in params for a in ("-p", p)], name=name)
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


def test_a_sample_sees_every_transition_added_before_it(launch, monkeypatch):
    """Bulk adds of 10 x reduce_batch, sets another client left in TM, stores not sent yet and transitions
    added since a prefetch: a draw of every entry holds every one of them."""
    name = start_memory(launch, "all", "reduce_batch:=50")
    o, a, r, o2, term, trunc = rows(500)
    with MemoryReplayBuffer(name, prefetch=4) as buf:
        buf.extend(o, a, r, o2, term, trunc)
        b = buf.sample(500)                                       # all 500, in one batch
        np.testing.assert_array_equal(np.sort(b["obs"][:, 0]), np.sort(o[:, 0].astype(np.float32)))
        assert len(np.unique(b["identity_id"])) == 500 and PENDING_IDENTITY not in b["identity_id"]
        s = buf.stats()
        assert s["tm_sets"] == 0 and s["rtm_size"] == 500 and len(buf) == 500
        # another client's 300 sets wait in TM: the buffer reduces until TM is empty, one call of 16 at a time
        with MemoryClient.standalone(name) as other:
            assert other.wait_for_service(30.0)
            xo, xa, xr, xo2, xt, xu = rows(300, seed=1)
            other.store(Transitions(xo.astype(np.float32) + 50, xa.astype(np.float32), xr.astype(np.float32),
                                    xo2.astype(np.float32), xt, xu, value_labels=np.zeros(300, np.float32)))
        monkeypatch.setattr(replay_buffer, "REDUCE_CHUNK", 16)
        buf.add(o[0] + 100, a[0], r[0], o2[0], False)
        reductions = buf.stats()["reductions"]
        b = buf.sample(801)
        assert np.sum(b["obs"][:, 0] > 25) == 301 and len(np.unique(b["obs"][:, 0])) == 801
        s = buf.stats()
        assert s["tm_sets"] == 0 and s["rtm_size"] == 801 and s["reductions"] - reductions >= 300 // 16
        # one transition added before each sample (not stored yet: store_every 64), drawn from the prefetched
        # batches with the new ones mixed in: a filled batch holds every entry, each of them included
        fetches = buf.fetches
        for i in range(10):
            buf.add(o[i] + 200, a[i], r[i], o2[i], False)
            b = buf.sample(900, fill=True)
            assert np.sum(np.unique(b["obs"][:, 0]) > 150) == i + 1 and len(np.unique(b["obs"][:, 0])) == 802 + i
        assert buf.fetches - fetches <= 4                         # 4 batches per fetch: most were prefetched
        pending = b["identity_id"] == PENDING_IDENTITY       # added after the fetch this batch came from
        assert pending.any() and np.all(b["obs"][pending, 0] > 150) and np.all(b["count"][pending] == 1)
    with MemoryReplayBuffer(name, prefetch=0, store_every=1000) as exact:    # a request per sample
        exact.add(o[0] + 300, a[0], r[0], o2[0], False)
        b = exact.sample(812)
        assert np.sum(b["obs"][:, 0] > 250) == 1 and PENDING_IDENTITY not in b["identity_id"]


def test_prefetched_batches_mix_in_new_transitions_as_a_uniform_draw(launch):
    """20 entries in the memory, 5 added after a prefetch of 64 batches of 8: the next 127 batches come from
    the fetched ones, and the new transitions are in them as often as a uniform draw of 8 out of 25 puts them."""
    name = start_memory(launch, "mix")
    o, a, r, o2, term, trunc = rows(25)
    with MemoryReplayBuffer(name, prefetch=64, seed=3) as buf:
        buf.extend(o[:20], a[:20], r[:20], o2[:20], term[:20], trunc[:20])
        buf.sample(8)
        buf.extend(o[20:], a[20:], r[20:], o2[20:], term[20:], trunc[20:])
        batches = [buf.sample(8) for _ in range(127)]      # the rest of the first fetch and all of the second
    seen = np.concatenate([b["obs"][:, 0] for b in batches])
    assert all(len(np.unique(b["obs"][:, 0])) == 8 for b in batches)
    assert set(seen.tolist()) == set(o[:, 0].astype(np.float32).tolist())
    new = np.isin(seen, o[20:, 0].astype(np.float32))
    assert np.array_equal(new, np.concatenate([b["identity_id"] for b in batches]) == PENDING_IDENTITY)
    assert 150 <= new.sum() <= 260        # 127 x 8 x 5 / 25 = 203.2, sd 12.7


def test_seeded_buffers_draw_the_same_batches_on_fresh_memories(launch):
    """The same seed, adds and samples on two fresh memory nodes: the same batches; another seed: others."""
    names = [start_memory(launch, f"seed{i}") for i in range(2)]
    o, a, r, o2, term, trunc = rows(300)

    def run(name, seed):
        with MemoryReplayBuffer(name, seed=seed, store_every=16, prefetch=4) as buf:
            buf.extend(o[:100], a[:100], r[:100], o2[:100], term[:100], trunc[:100])
            out = []
            for i in range(100, 300):
                buf.add(o[i], a[i], r[i], o2[i], term[i], trunc[i])
                out.append(buf.sample(32)["obs"])
            return np.stack(out)

    first, second = run(names[0], 7), run(names[1], 7)
    np.testing.assert_array_equal(first, second)
    assert not np.array_equal(run(names[0], 8), first)


def test_background_store_refused_by_the_node_raises_at_the_next_call(launch):
    name = start_memory(launch, "refuse")
    o, a, r, o2, term, trunc = rows(20)
    with MemoryReplayBuffer(name, store_every=4) as first:
        first.extend(o, a, r, o2, term, trunc)
        first.flush()
        with pytest.raises(ValueError, match="differ from this buffer"):      # within one buffer: at once
            first.add(np.zeros(4), a[0], r[0], np.zeros(4), False)
    with MemoryReplayBuffer(name, store_every=4) as second:                   # another buffer, another shape
        second.extend(np.zeros((4, 4)), a[:4], r[:4], np.ones((4, 4)), term[:4])
        with pytest.raises(MemoryServiceError, match="store refused"):
            second.sample(8)
        assert len(second) == 20                                               # nothing of it stored


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


def run_example(name, out, seed=0):
    proc = subprocess.run([sys.executable, str(ROOT / "examples" / "sb3_td3_through_memory.py"),
                           "--env-id", "Pendulum-v1", "--total-steps", "300", "--learning-starts", "100",
                           "--seed", str(seed), "--memory-node", name, "--eval-episodes", "2", "--out", str(out)],
                          capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    return json.loads(out.read_text())


def test_sb3_td3_example_trains_through_a_memory_node_and_repeats_with_its_seed(launch, tmp_path):
    """Two runs with one seed, each on a fresh memory node in another process: the same evaluation."""
    first = run_example(start_memory(launch, "td3a"), tmp_path / "a.json")
    second = run_example(start_memory(launch, "td3b"), tmp_path / "b.json")
    for summary in (first, second):
        m = summary["memory"]
        assert m["transitions_stored"] == 300 and 0 < m["identities"] <= 300
        assert m["reductions"] >= 1 and m["rate_samples"] >= 200 * 100     # a batch per gradient step
        assert len(summary["eval_returns"]) == 2
    assert first["eval_returns"] == second["eval_returns"]
    assert first["memory"] == second["memory"]

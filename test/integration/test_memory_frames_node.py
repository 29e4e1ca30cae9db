"""The frame store through memory_node (`ros2 run`, issue 59): stacked uint8 frames stored over the services are
kept once each (``bytes_used``), sampled back byte for byte, and a SIGKILL loses none of them (WAL of frame
records + snapshots of the frame store)."""
from __future__ import annotations

import os
import signal
from pathlib import Path

import numpy as np

from comper_memory.client import MemoryClient
from comper_msgs_py.arrays import Transitions

MEMORY_YAML = Path(__file__).resolve().parents[2] / "src" / "comper_memory" / "config" / "memory.yaml"


def stacked_stream(n: int, seed: int = 0) -> Transitions:
    """n transitions of 4 stacked 84x84 frames, oldest first; every 50 steps a new episode whose first stack
    repeats its first frame."""
    rng = np.random.default_rng(seed)
    frames = rng.integers(0, 256, (n + 1, 84, 84), dtype=np.uint8)
    start = (np.arange(n) // 50) * 50
    back = np.arange(-3, 1)
    s = frames[np.maximum(np.arange(n)[:, None] + back, start[:, None])]
    s2 = frames[np.maximum(np.arange(n)[:, None] + 1 + back, start[:, None])]
    ends = (np.arange(n) % 50) == 49
    return Transitions(s, rng.integers(0, 18, n), rng.standard_normal(n).astype(np.float32), s2, ends,
                       np.zeros(n, bool), value_labels=rng.standard_normal(n).astype(np.float32))


def test_stacked_frames_through_the_node_survive_sigkill(launch, tmp_path):
    params = ("-p", f"storage_dir:={tmp_path / 'storage'}", "-p", "snapshot_every:=5")
    name = f"memory_frames_{os.getpid()}"
    clients = []

    def start(tag):
        proc = launch("comper_memory", "memory_node", "--ros-args", "--params-file", str(MEMORY_YAML), *params,
                      "-r", f"__node:={name}{tag}", name=f"{name}{tag}")
        clients.append(MemoryClient.standalone(f"{name}{tag}", timeout=30.0))
        assert clients[-1].wait_for_service(30.0), proc.log()
        return proc, clients[-1]

    t = stacked_stream(400)
    try:
        run(start, t)
    finally:
        for c in clients:
            c.close()


def run(start, t):
    proc, memory = start("a")
    ids_stored = np.concatenate([memory.store(t.take(np.arange(i, i + 40))).identity_ids for i in range(0, 400, 40)])
    stats = memory.stats()
    assert stats["identities"] == 400 and np.all(np.diff(ids_stored.astype(np.int64)) == 1)
    assert stats["bytes_used"] < 15e6       # each frame once; whole stacks: 1,024 slots x 56 KB = 58 MB
    drawn, ids, _ = memory.sample(64, source="tm", seed=3)
    proc.kill(signal.SIGKILL)

    proc2, memory2 = start("b")
    assert memory2.stats()["identities"] == 400
    again, ids2, _ = memory2.sample(64, source="tm", seed=3)
    np.testing.assert_array_equal(ids2, ids)
    np.testing.assert_array_equal(again.states, drawn.states)
    np.testing.assert_array_equal(again.next_states, drawn.next_states)
    row = np.searchsorted(ids_stored, ids)                           # each transition is its own identity
    np.testing.assert_array_equal(again.states, t.states[row])
    assert memory2.store(t.take(np.arange(32))).new_identities == 0  # re-stored: found again, nothing new
    proc2.kill(signal.SIGTERM)
    assert proc2.proc.returncode == 0, proc2.log()

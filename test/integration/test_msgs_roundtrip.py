"""comper_msgs round-trip between two processes, and the numpy conversions on the way."""
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from rclpy.qos import QoSProfile, ReliabilityPolicy

from conftest import spin_once
from comper_msgs.msg import EpisodeSummary, QTModel, TransitionBatch
from comper_msgs_py.arrays import Transitions
from comper_msgs_py.convert import (array_to_numpy, batch_to_transitions, numpy_to_array,
                                    transitions_to_batch)

HERE = Path(__file__).parent


@pytest.fixture
def echo(tmp_path):
    procs = []

    def _start(type_name, node_name):
        log = open(tmp_path / f"{node_name}.log", "wb")
        p = subprocess.Popen([sys.executable, str(HERE / "echo_node.py"), type_name, "--node-name", node_name],
                             stdout=log, stderr=subprocess.STDOUT, env=os.environ.copy())
        procs.append((p, log))
        return p

    yield _start
    for p, log in procs:
        p.terminate()
        try:
            p.wait(timeout=10)
        except subprocess.TimeoutExpired:
            p.kill()
        log.close()


def _roundtrip(node, echo, msg_type, type_name, msg, timeout=30.0):
    name = f"echo_{type_name.split('/')[-1].lower()}_{os.getpid()}"
    echo(type_name, name)
    qos = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
    pub = node.create_publisher(msg_type, f"/{name}/in", qos)
    got = []
    node.create_subscription(msg_type, f"/{name}/out", got.append, qos)
    deadline = time.monotonic() + timeout
    while not got and time.monotonic() < deadline:
        if pub.get_subscription_count() > 0:
            pub.publish(msg)
        spin_once(node, timeout=0.2)
    assert got, f"no echo of {type_name} within {timeout} s"
    return got[0]


def _atari_batch(n=8, rng=np.random.default_rng(0)):
    return Transitions(
        states=rng.integers(0, 256, (n, 84, 84), dtype=np.uint8),
        actions=rng.integers(0, 18, n).astype(np.float32),
        rewards=rng.normal(size=n).astype(np.float32),
        next_states=rng.integers(0, 256, (n, 84, 84), dtype=np.uint8),
        terminated=rng.random(n) < 0.3, truncated=rng.random(n) < 0.3,
        value_labels=rng.normal(size=n).astype(np.float32),
        episode_ids=np.arange(n, dtype=np.uint64), steps=np.arange(n, dtype=np.uint64) * 7,
        run_id="run-a")


def test_transition_batch_roundtrip_between_processes(ros_node, echo):
    t = _atari_batch()
    out = _roundtrip(ros_node, echo, TransitionBatch, "comper_msgs/msg/TransitionBatch", transitions_to_batch(t))
    back = batch_to_transitions(out)
    assert back.states.dtype == np.uint8 and back.states.shape == (8, 84, 84)
    for name in ("states", "actions", "rewards", "next_states", "terminated", "truncated",
                 "value_labels", "episode_ids", "steps"):
        np.testing.assert_array_equal(getattr(back, name), getattr(t, name), err_msg=name)
    assert back.run_id == "run-a"


def test_qt_model_and_episode_summary_roundtrip(ros_node, echo):
    w = np.random.default_rng(1).normal(size=(64, 26)).astype(np.float32)
    msg = QTModel(version=3, architecture="comcact", key_size=26, sequence_length=1,
                  tensor_names=["lstm.weight"], tensors=[numpy_to_array(w)], label_mean=1.5, label_std=2.0)
    out = _roundtrip(ros_node, echo, QTModel, "comper_msgs/msg/QTModel", msg)
    assert out.version == 3 and list(out.tensor_names) == ["lstm.weight"]
    np.testing.assert_array_equal(array_to_numpy(out.tensors[0]), w)

    ep = EpisodeSummary(run_id="r", env_id="Hopper-v4", source="train", episode_id=4, episode_return=12.5,
                        length=100, frames=100, terminated=True, truncated=False, global_step=1000)
    out = _roundtrip(ros_node, echo, EpisodeSummary, "comper_msgs/msg/EpisodeSummary", ep)
    assert (out.episode_return, out.length, out.terminated, out.truncated) == (12.5, 100, True, False)

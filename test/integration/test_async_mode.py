"""comcact_node mode:=async over real ROS 2 (no mocks): the learner in one process (embedded memory
and QT trainer), two actor_node processes it starts storing into the memory, the policy on
~/policy, the memory's rate limiter holding the update-to-data ratio while the learner re-stores its
batches with fresh labels (profile fresh_labels_gate); and an actor started separately against nodes
started separately (thesis defaults)."""
from __future__ import annotations

import os
import re
import signal
import time

import numpy as np
import torch

from comper_agent.nodes import run_io
from comper_agent.core.comcact import ComcactLearner
from comper_agent.core.config import ComcactConfig
from comper_agent.nodes.policy_weights import POLICY_QOS, config_of_policy, load_policy_msg
from comper_msgs.msg import EpisodeSummary, PolicyWeights
from comper_msgs_py.arrays import Transitions
from comper_msgs_py.qos import RECORDED_QOS as SUMMARY_QOS
from conftest import spin_once

TASK = "InvertedPendulum-v4"


def _wait(proc, timeout):
    try:
        return proc.proc.wait(timeout=timeout)
    except Exception:
        raise AssertionError(f"{proc.name} did not finish within {timeout} s:\n{proc.log()[-4000:]}")


def test_async_learner_with_two_actor_processes(launch, ros_node, tmp_path):
    name = f"comcact_async_{os.getpid()}"
    policies: list[PolicyWeights] = []
    ros_node.create_subscription(PolicyWeights, f"/{name}/policy", policies.append, POLICY_QOS)
    proc = launch("comper_agent", "comcact_node", "--ros-args", "-p", f"env_id:={TASK}", "-p", "mode:=async",
                  "-p", "num_actors:=2", "-p", "total_steps:=600", "-p", "eval_every:=300", "-p", "eval_episodes:=1",
                  "-p", "policy_period_s:=0.5", "-p", "rate_buffer_steps:=40", "-p", f"runs_root:={tmp_path}",
                  "-p", "run_id:=as", "-p", "tensorboard:=false", "-p", "progress_period_s:=2.0",
                  "-p", "transport_probe_calls:=0", "-p", "profile:=fresh_labels_gate",
                  "-r", f"comcact_node:__node:={name}", name=name)
    deadline = time.monotonic() + 400
    while time.monotonic() < deadline and proc.alive():
        spin_once(ros_node, 0.2)
    assert _wait(proc, 30) == 0, proc.log()[-4000:]
    for _ in range(20):
        spin_once(ros_node, 0.1)
    run = tmp_path / "as"
    actors = run_io.MetricsLog.read(run / "metrics.jsonl", "actors")[-1]
    assert actors["exit_codes"] == [0, 0], proc.log()[-3000:]
    assert actors["env_steps"] >= 600
    # the rate limiter: 64 samples per stored transition within 40 steps either side (+ the learning start);
    # the learner's re-stores (64 per update, marked relabel) are neither environment steps nor inserts
    assert abs(actors["updates"] - actors["env_steps"]) <= 40 + 64 + 10, actors
    assert actors["relabelled"] >= 32 * actors["updates"] > 0, actors
    logs = [(run / f"actor_{i}.log").read_text() for i in range(2)]
    for i, text in enumerate(logs):
        assert f"actor {i} on {TASK}" in text and "done: 300 steps" in text, text[-2000:]
    evals = [e["step"] for e in run_io.MetricsLog.read(run / "metrics.jsonl", "eval")]
    assert evals[0] == 0 and len(evals) >= 3 and evals[-1] >= 600
    # the policy topic: versions grow, the last message says final and holds the learner's final actor
    assert policies and policies[-1].final and policies[0].version < policies[-1].version
    assert all(a.version <= b.version for a, b in zip(policies, policies[1:]))
    state = torch.load(run / "checkpoints" / "latest.pt", weights_only=True)["state"]["learner"]
    cfg = config_of_policy(policies[-1], ComcactConfig)
    low, high = np.array([-3.0], np.float32), np.array([3.0], np.float32)
    from_msg, from_ckpt = ComcactLearner(cfg, 4, low, high), ComcactLearner(cfg, 4, low, high)
    load_policy_msg(from_msg, policies[-1])
    for part in ("actor", "actor_target", "critic_target"):   # target labels: the actors get the target networks
        getattr(from_ckpt, part).load_state_dict(state[part])
    obs = np.random.default_rng(0).normal(size=(16, 4)).astype(np.float32)
    np.testing.assert_allclose(from_msg.act(obs, explore=False), from_ckpt.act(obs, explore=False), atol=1e-6)
    t = Transitions(obs, from_msg.act(obs, explore=False), np.zeros(16, np.float32), obs[::-1].copy(),
                    np.zeros(16, bool), np.zeros(16, bool))
    np.testing.assert_allclose(from_msg.value_labels(t), from_ckpt.value_labels(t), atol=1e-5)


def test_actor_started_separately_stores_into_a_separate_memory_node(launch, ros_node, tmp_path):
    """bringup:=external with num_actors 0: memory_node, qt_trainer_node, sim_node, the learner and one
    actor_node each started with ros2 run; the actor stops on the learner's final policy message, and a
    subscriber of its ~/episodes receives every episode it reports, the last one included."""
    tag = os.getpid()
    sim, mem, qt, learner = f"sim_a{tag}", f"mem_a{tag}", f"qt_a{tag}", f"learner_a{tag}"
    launch("comper_sim", "sim_node", "--ros-args", "-p", f"env_id:={TASK}", "-r", f"__node:={sim}", name=sim)
    launch("comper_memory", "memory_node", "--ros-args", "-r", f"__node:={mem}", "-p", "samples_per_insert:=64.0",
           "-p", "rate_error_buffer:=6400.0", "-p", "min_size_to_sample:=64", name=mem)
    launch("comper_agent", "qt_trainer_node", "--ros-args", "-p", f"memory_node:={mem}", "-r", f"__node:={qt}",
           name=qt)
    proc = launch("comper_agent", "comcact_node", "--ros-args", "-p", f"env_id:={TASK}", "-p", "mode:=async",
                  "-p", "bringup:=external", "-p", "num_actors:=0", "-p", f"sim_node:={sim}", "-p", f"memory_node:={mem}",
                  "-p", f"qt_trainer_node:={qt}", "-p", "total_steps:=300", "-p", "eval_every:=0",
                  "-p", f"runs_root:={tmp_path}", "-p", "run_id:=ext", "-p", "tensorboard:=false",
                  "-p", "transport_probe_calls:=0", "-p", "startup_timeout_s:=60", "-r", f"comcact_node:__node:={learner}",
                  name=learner)
    episodes: list[EpisodeSummary] = []
    ros_node.create_subscription(EpisodeSummary, f"/actor_x{tag}/episodes", episodes.append, SUMMARY_QOS)
    actor = launch("comper_agent", "actor_node", "--ros-args", "-p", f"env_id:={TASK}", "-p", "seed:=5",
                   "-p", f"memory_node:={mem}", "-p", f"policy_topic:=/{learner}/policy", "-r", f"__node:=actor_x{tag}",
                   name=f"actor_x{tag}")
    deadline = time.monotonic() + 400
    while time.monotonic() < deadline and actor.alive():
        spin_once(ros_node, 0.2)
    assert _wait(proc, 60) == 0, proc.log()[-4000:]
    assert _wait(actor, 60) == 0, actor.log()[-3000:]
    for _ in range(20):
        spin_once(ros_node, 0.1)
    log = actor.log()
    assert "final policy message" in log
    reported = int(re.search(r"done: \d+ steps \([^)]*\), (\d+) episodes", log).group(1))
    assert reported > 0 and len(episodes) == reported, (len(episodes), log[-2000:])
    assert "had not acknowledged" not in log
    state = torch.load(tmp_path / "ext" / "checkpoints" / "latest.pt", weights_only=True)["state"]
    assert state["counters"]["step"] >= 300 and state["counters"]["reductions"] >= 1
    assert state["learner"]["qt_steps"] > 0

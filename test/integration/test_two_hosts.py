"""Several hosts, on one machine: two network namespaces joined by a veth pair stand for two hosts
(their own interfaces, addresses and loopback; DDS discovery by multicast over the link, UDP
transport only, as between real hosts). The memory, QT trainer, sim and learner (mode:=async) run
in one namespace, an actor_node in the other. Needs root (a test creates and removes its own
namespaces) and iproute2; skipped otherwise."""
from __future__ import annotations

import os
import shutil
import subprocess

import pytest
import torch

TASK = "InvertedPendulum-v4"
# what real hosts need (docs/comcact.md, "Several hosts"): the same domain id, discovery beyond
# localhost, and UDP (shared memory only reaches processes of one host)
HOST_ENV = {"ROS_AUTOMATIC_DISCOVERY_RANGE": "SUBNET", "FASTDDS_BUILTIN_TRANSPORTS": "UDPv4"}


def _ip(*args):
    subprocess.run(["ip", *args], check=True, capture_output=True, text=True)


@pytest.fixture
def two_hosts():
    if os.geteuid() != 0 or shutil.which("ip") is None:
        pytest.skip("needs root and iproute2 to create network namespaces")
    tag = os.getpid() % 100000
    a, b = f"cmp{tag}a", f"cmp{tag}b"
    net = f"10.{200 + tag % 50}.{tag % 250}"
    try:
        _ip("netns", "add", a)
        _ip("netns", "add", b)
        _ip("link", "add", f"v{tag}a", "type", "veth", "peer", "name", f"v{tag}b")
        for ns, dev, host in ((a, f"v{tag}a", 1), (b, f"v{tag}b", 2)):
            _ip("link", "set", dev, "netns", ns)
            _ip("-n", ns, "addr", "add", f"{net}.{host}/24", "dev", dev)
            _ip("-n", ns, "link", "set", dev, "up")
            _ip("-n", ns, "link", "set", "lo", "up")
    except subprocess.CalledProcessError as exc:
        for ns in (a, b):
            subprocess.run(["ip", "netns", "del", ns], capture_output=True)
        pytest.skip(f"cannot create network namespaces here: {exc.stderr.strip()}")
    yield ("ip", "netns", "exec", a), ("ip", "netns", "exec", b)
    for ns in (a, b):
        subprocess.run(["ip", "netns", "del", ns], capture_output=True)   # removes the veth pair too


def test_actor_on_another_host_feeds_the_learner_and_memory(launch, two_hosts, tmp_path):
    host_a, host_b = two_hosts
    tag = os.getpid()
    sim, mem, qt, learner = f"sim_h{tag}", f"mem_h{tag}", f"qt_h{tag}", f"learner_h{tag}"
    on_a = {"prefix": host_a, "env": HOST_ENV}
    launch("comper_sim", "sim_node", "--ros-args", "-p", f"env_id:={TASK}", "-r", f"__node:={sim}", name=sim, **on_a)
    launch("comper_memory", "memory_node", "--ros-args", "-r", f"__node:={mem}", "-p", "samples_per_insert:=64.0",
           "-p", "rate_error_buffer:=6400.0", "-p", "min_size_to_sample:=64", name=mem, **on_a)
    launch("comper_agent", "qt_trainer_node", "--ros-args", "-p", f"memory_node:={mem}", "-r", f"__node:={qt}",
           name=qt, **on_a)
    proc = launch("comper_agent", "comcact_node", "--ros-args", "-p", f"env_id:={TASK}", "-p", "mode:=async",
                  "-p", "bringup:=external", "-p", "num_actors:=0", "-p", f"sim_node:={sim}", "-p", f"memory_node:={mem}",
                  "-p", f"qt_trainer_node:={qt}", "-p", "total_steps:=300", "-p", "eval_every:=0",
                  "-p", f"runs_root:={tmp_path}", "-p", "run_id:=hosts", "-p", "tensorboard:=false",
                  "-p", "transport_probe_calls:=0", "-p", "startup_timeout_s:=90", "-r", f"comcact_node:__node:={learner}",
                  name=learner, **on_a)
    actor = launch("comper_agent", "actor_node", "--ros-args", "-p", f"env_id:={TASK}", "-p", "seed:=9",
                   "-p", f"memory_node:={mem}", "-p", f"policy_topic:=/{learner}/policy", "-p", "startup_timeout_s:=90",
                   "-r", f"__node:=actor_h{tag}", name=f"actor_h{tag}", prefix=host_b, env=HOST_ENV)
    try:
        assert proc.proc.wait(timeout=420) == 0, proc.log()[-4000:]
        assert actor.proc.wait(timeout=90) == 0, actor.log()[-3000:]
    except subprocess.TimeoutExpired:
        raise AssertionError(f"did not finish:\n{proc.log()[-3000:]}\n--- actor:\n{actor.log()[-2000:]}")
    assert "final policy message" in actor.log()
    state = torch.load(tmp_path / "hosts" / "checkpoints" / "latest.pt", weights_only=True)["state"]
    assert state["counters"]["step"] >= 300 and state["learner"]["qt_steps"] > 0

"""sim_node in its own process (`ros2 run comper_sim sim_node`), driven over real ROS 2 services
from this test process: reset / step / step_many / info for Hopper-v4 and ALE/Freeway-v5, bad
requests answered with success=false and a message while the node keeps serving, the episodes
topic, the parameter file, a clean Ctrl-C and a readable failure for an unknown env id."""
import json
import os
import time
from pathlib import Path

import numpy as np
import pytest

from comper_msgs.msg import Array, EpisodeSummary
from comper_msgs.srv import EnvInfo, Reset, Step, StepMany
from comper_msgs_py.convert import array_to_numpy, batch_to_transitions, numpy_to_array
from comper_sim.sim_node import EPISODES_QOS
from conftest import call, spin_once

ROOT = Path(__file__).resolve().parents[2]
SIM_YAML = ROOT / "src" / "comper_sim" / "config" / "sim.yaml"
ATARI_YAML = ROOT / "src" / "comper_sim" / "config" / "atari.yaml"


class Sim:
    """Clients for one sim_node, named `name` (the node's services are private: /name/...)."""

    def __init__(self, node, name):
        self.node = node
        self.reset_c = node.create_client(Reset, f"/{name}/reset")
        self.step_c = node.create_client(Step, f"/{name}/step")
        self.many_c = node.create_client(StepMany, f"/{name}/step_many")
        self.info_c = node.create_client(EnvInfo, f"/{name}/info")

    def reset(self, seed=-1):
        return call(self.node, self.reset_c, Reset.Request(seed=seed))

    def step(self, action=None, msg=None):
        req = Step.Request()
        req.action = msg if msg is not None else numpy_to_array(np.asarray(action, np.float32))
        return call(self.node, self.step_c, req)

    def step_many(self, actions=None, autoreset=True, msg=None):
        req = StepMany.Request(autoreset=autoreset)
        req.actions = msg if msg is not None else numpy_to_array(np.asarray(actions, np.float32))
        return call(self.node, self.many_c, req)

    def info(self):
        return call(self.node, self.info_c, EnvInfo.Request(), timeout=60.0)


def start(launch, tag, *params):
    name = f"sim_{tag}_{os.getpid()}"
    proc = launch("comper_sim", "sim_node", "--ros-args", *params, "-r", f"__node:={name}", name=name)
    return proc, name


def assert_refused(resp, proc, *words):
    assert resp.success is False, "a bad request was accepted"
    assert resp.message, "a refused request must say why"
    for w in words:
        assert w in resp.message, f"{w!r} not in {resp.message!r}"
    assert proc.alive(), f"the node died on a bad request:\n{proc.log()}"


def malformed_array():
    a = Array(dtype=Array.DTYPE_FLOAT32, shape=[3])
    a.data_f32 = [0.0, 0.0]                       # 2 values for shape [3]
    return a


def test_hopper_serves_refuses_bad_requests_publishes_episodes_and_stops_cleanly(launch, ros_node):
    proc, name = start(launch, "hopper", "--params-file", str(SIM_YAML), "-p", "env_id:=Hopper-v4",
                       "-p", "seed:=3")
    summaries = []
    ros_node.create_subscription(EpisodeSummary, f"/{name}/episodes", summaries.append, EPISODES_QOS)
    sim = Sim(ros_node, name)

    info = sim.info()
    assert info.env_id == "Hopper-v4" and list(info.observation_shape) == [11]
    assert info.observation_dtype == Array.DTYPE_FLOAT32 and not info.discrete
    assert list(info.action_shape) == [3] and list(info.action_low) == [-1.0] * 3
    assert info.max_episode_steps == 1000 and info.frame_skip == 1 and info.episode_end == "standard"
    assert json.loads(info.spec_json)["seed"] == 3

    # before any reset a step is refused
    assert_refused(sim.step([0, 0, 0]), proc, "reset")
    r = sim.reset()
    assert r.success and r.episode_id == 0
    obs0 = array_to_numpy(r.observation)
    assert obs0.shape == (11,) and obs0.dtype == np.float32

    s = sim.step([0.1, -0.1, 0.2])
    assert s.success and s.episode_step == 1 and s.frames == 1 and not s.terminated and not s.truncated
    assert array_to_numpy(s.observation).shape == (11,)

    # every bad request: success=false, a message, the node still serves, nothing changed
    assert_refused(sim.step([0, 0]), proc, "shape")
    assert_refused(sim.step([0, np.nan, 0]), proc, "NaN")
    assert_refused(sim.step([0, np.inf, 0]), proc, "NaN")
    assert_refused(sim.step([0, 0, 1.5]), proc, "bounds")
    assert_refused(sim.step(msg=malformed_array()), proc, "needs 3 values")
    assert_refused(sim.step(msg=Array(dtype=9, shape=[3])), proc, "dtype")
    assert_refused(sim.step_many(np.zeros((4, 2))), proc, "shape")
    assert_refused(sim.step_many(np.zeros((0, 3))), proc, "empty")
    assert_refused(sim.step_many(np.vstack([np.zeros((2, 3)), [[0, 0, np.nan]]])), proc, "row 2")
    s = sim.step([0.0, 0.0, 0.0])
    assert s.success and s.episode_step == 2 and s.episode_id == 0

    # step_many: K transitions as one TransitionBatch; a hopper pushed hard falls, episodes end
    actions = np.tile(np.array([1.0, -1.0, 1.0], np.float32), (300, 1))
    m = sim.step_many(actions, autoreset=True)
    assert m.success and m.episodes_ended >= 1
    t = batch_to_transitions(m.transitions)
    assert len(t) == 300 and t.states.shape == (300, 11) and t.states.dtype == np.float32
    np.testing.assert_array_equal(t.actions, actions)
    assert t.terminated.sum() == m.episodes_ended and t.value_labels.size == 0
    np.testing.assert_array_equal(t.steps, np.arange(2, 302, dtype=np.uint64))
    assert array_to_numpy(m.observation).shape == (11,)

    deadline = time.monotonic() + 15
    while len(summaries) < m.episodes_ended and time.monotonic() < deadline:
        spin_once(ros_node, 0.1)
    assert len(summaries) == m.episodes_ended, "no EpisodeSummary for every ended episode"
    first = summaries[0]
    in_first = t.episode_ids == 0
    assert first.source == "sim" and first.env_id == "Hopper-v4" and first.episode_id == 0
    assert first.terminated and not first.truncated
    assert first.length == 2 + in_first.sum() and first.frames == first.length
    assert first.global_step == first.length

    # without autoreset stepping stops at the end, then a step is refused until reset
    m = sim.step_many(actions, autoreset=False)
    assert m.success and m.episodes_ended == 1 and len(m.transitions.rewards) < 300
    assert_refused(sim.step([0, 0, 0]), proc, "reset")
    r = sim.reset(seed=3)
    assert r.success and np.array_equal(array_to_numpy(r.observation), obs0)   # same seed, same start

    rc = proc.stop()
    log = proc.log_path.read_text(errors="replace")
    assert rc == 0, f"Ctrl-C did not end the node cleanly (exit {rc}):\n{log}"
    assert "Traceback" not in log, log


def test_freeway_serves_the_atari_protocol(launch, ros_node):
    proc, name = start(launch, "freeway", "--params-file", str(ATARI_YAML), "-p", "env_id:=ALE/Freeway-v5")
    sim = Sim(ros_node, name)
    info = sim.info()
    spec = json.loads(info.spec_json)
    assert info.discrete and info.num_actions == 18 and info.frame_skip == 5
    assert list(info.observation_shape) == [84, 84] and info.observation_dtype == Array.DTYPE_UINT8
    assert spec["repeat_action_probability"] == pytest.approx(0.25) and spec["life_loss_signal"] is False

    r = sim.reset()
    obs = array_to_numpy(r.observation)
    assert r.success and obs.shape == (84, 84) and obs.dtype == np.uint8
    s = sim.step(np.float32(2))
    assert s.success and s.frames == 5 and s.episode_step == 1

    assert_refused(sim.step(np.float32(18)), proc, "outside [0, 18)")
    assert_refused(sim.step(np.float32(-1)), proc, "outside")
    assert_refused(sim.step(np.float32(2.5)), proc, "whole number")
    assert_refused(sim.step([1, 2]), proc, "one index")
    assert_refused(sim.step_many(np.array([1, 2, 40])), proc, "row 2")

    m = sim.step_many(np.random.default_rng(0).integers(0, 18, 40))
    assert m.success
    t = batch_to_transitions(m.transitions)
    assert t.states.shape == (40, 84, 84) and t.states.dtype == np.uint8 and t.actions.shape == (40,)
    s = sim.step(np.float32(0))
    assert s.success and s.episode_step == 42 and s.frames == 42 * 5
    assert proc.alive()


def test_frame_stack_parameter(launch, ros_node):
    proc, name = start(launch, "stack", "-p", "env_id:=ALE/Freeway-v5", "-p", "frame_stack:=4")
    sim = Sim(ros_node, name)
    assert list(sim.info().observation_shape) == [4, 84, 84]
    sim.reset()
    m = sim.step_many(np.zeros(3))
    assert batch_to_transitions(m.transitions).next_states.shape == (3, 4, 84, 84)


@pytest.mark.parametrize("params,words", [
    (("-p", "env_id:=NoSuchEnv-v0"), ("NoSuchEnv-v0",)),
    (("-p", "env_id:=Pendulum-v1", "-p", "episode_end:=sometimes"), ("episode_end", "sometimes")),
], ids=["unknown-env", "bad-parameter"])
def test_bad_start_exits_nonzero_with_a_readable_message(launch, params, words):
    proc, _ = start(launch, "bad", *params)
    try:
        rc = proc.proc.wait(timeout=60)
    except Exception:
        pytest.fail(f"the node did not exit:\n{proc.log()}")
    log = proc.log()
    assert rc != 0
    assert "cannot start" in log and all(w in log for w in words), log
    assert "Traceback" not in log, log


def test_embedded_in_process_with_node_kwargs(ros_node):
    """Other nodes can embed SimNode in their own process (context, parameter_overrides, namespace)."""
    from rclpy.parameter import Parameter

    from comper_sim.sim_node import SimNode
    sim_node = SimNode(context=ros_node.context, namespace="/embedded",
                       parameter_overrides=[Parameter("env_id", value="Pendulum-v1"),
                                            Parameter("max_episode_steps", value=5)])
    ros_node.test_executor.add_node(sim_node)
    try:
        reset_c = ros_node.create_client(Reset, "/embedded/sim_node/reset")
        many_c = ros_node.create_client(StepMany, "/embedded/sim_node/step_many")
        assert call(ros_node, reset_c, Reset.Request(seed=1)).success
        req = StepMany.Request(autoreset=False)
        req.actions = numpy_to_array(np.zeros((9, 1), np.float32))
        res = call(ros_node, many_c, req)
        assert res.success and res.episodes_ended == 1 and list(res.transitions.truncated) == [False] * 4 + [True]
    finally:
        ros_node.test_executor.remove_node(sim_node)
        sim_node.destroy_node()


def test_sim_client_steps_and_raises_typed_errors(launch):
    """The client the learners use (comper_sim.client.SimClient): numpy in and out, a refused request
    raises ServiceRefused with the node's reason, a missing server ServiceUnavailable."""
    from comper_msgs_py.service_client import ServiceRefused, ServiceTimeout, ServiceUnavailable, wait_for_services
    from comper_sim.client import SimClient
    proc, name = start(launch, "client", "-p", "env_id:=Hopper-v4", "-p", "seed:=3")
    with SimClient.standalone(name, timeout=60.0) as sim:
        assert sim.wait_for_service(60.0), proc.log()
        assert sim.info().env_id == "Hopper-v4"
        obs = sim.reset(0, dtype=np.float32)
        assert obs.shape == (11,) and obs.dtype == np.float32
        r = sim.step(np.zeros(3, np.float32))
        assert r.observation.shape == (11,) and isinstance(r.reward, float) and r.episode_step == 1
        many = sim.step_many(np.zeros((5, 3), np.float32))
        assert len(many.transitions) == 5 and many.observation.shape == (11,)
        with pytest.raises(ServiceRefused) as err:
            sim.step(np.zeros(7, np.float32))                    # wrong action size: refused, node keeps serving
        assert err.value.message and "refused" in str(err.value)
        assert sim.step(np.zeros(3, np.float32)).episode_step >= 2
    with SimClient.standalone(f"no_such_sim_{os.getpid()}", timeout=0.5) as ghost:
        with pytest.raises(ServiceUnavailable, match="not available"):
            wait_for_services({"sim": ghost.step_client()}, 0.5)
        with pytest.raises(ServiceTimeout):                      # nobody answers: a TimeoutError too
            ghost.info(timeout=0.5)

"""The learner nodes' shared parameters (harness.declare_learner_parameters) and entry point, without a running ROS graph
(the start-up error test runs the node in a separate process)."""
import dataclasses
import functools
import io
import os
import signal
import subprocess
import sys
import threading
import time

import pytest

from comper_agent.nodes.agent_main import StopRequests, help_text
from comper_agent.nodes.node_config import AgentRunConfig, redefault
from comper_sim.core import episode_over
from comper_agent.nodes.comcact_node import ComcactNode, ComcactNodeConfig
from comper_agent.nodes.comper_node import ComperNode, ComperNodeConfig
from comper_agent.tools.supervisor import Supervisor
from comper_msgs_py.params import ConfigError, config_from_dict, config_to_dict

_COMMON = {"bringup": "embedded", "episode_end": "standard", "runs_root": "runs", "run_id": "", "resume": "",
           "keep_checkpoints": 3, "tensorboard": True, "record": False, "record_storage": "mcap", "record_compression": "zstd",
           "record_process": "child",
           "record_window": 50, "record_wait_s": 60.0,
           "publish_transitions": True, "sim_node": "sim_node", "memory_node": "memory_node",
           "qt_trainer_node": "qt_trainer_node", "service_timeout_s": 120.0, "startup_timeout_s": 30.0,
           "transport_probe_calls": 200, "prefetch_batches": 32, "reduce_overlap": False,
           "eval_episodes": 10, "eval_seed": -1,
           "checkpoint_replay": True,                      # added with the memory / replay in checkpoints
           "diagnostics_every": 250}                       # comcact only before COMPER's qt_diagnostics

# every parameter the nodes declared before the refactoring, with its default (record: comcact only,
# publish_transitions: comper only, before; both nodes have both now)
COMCACT = {**_COMMON, "algorithm": "comcact", "env_id": "InvertedPendulum-v4", "total_steps": 50_000,
           "warmup_steps": 0, "store_every": 10, "reduce_every": 10, "reduce_batch": 50_000, "qt_epochs": 0,
           "qt_targets": "local", "qt_wait_s": 2.0, "eval_every": 5_000, "eval_episodes": 10, "eval_seed": -1,
           "checkpoint_every": 0, "progress_period_s": 5.0, "restore_batch": False,
           "mode": "lockstep", "num_actors": 1, "policy_period_s": 1.0, "replay_ratio": 1.0, "rate_buffer_steps": 200,
           "profile": "auto"}                                               # added with COMCACT_PROFILES
COMPER = {**_COMMON, "algorithm": "comper", "env_id": "ALE/Freeway-v5", "total_frames": 100_000, "max_steps": 0,
          "reduce_every": 100, "reduce_batch": 1_000, "qt_epochs": 0, "qt_targets": "local", "qt_wait_s": 5.0,
          "reducer": "auto", "restore_batch": True, "store_every": 4, "stats_every": 1_000,
          "checkpoint_every": 5_000, "progress_period_s": 10.0,
          "profile": "auto", "eval_every": -1, "eval_epsilon": 0.0}     # added with the vector tasks


@pytest.mark.parametrize("cls, expected", [(ComcactNodeConfig, COMCACT), (ComperNodeConfig, COMPER)])
def test_node_configs_keep_every_parameter_name_and_default(cls, expected):
    assert config_to_dict(cls()) == expected
    assert issubclass(cls, AgentRunConfig) and dataclasses.is_dataclass(cls)


@pytest.mark.parametrize("cls, name, bad", [
    (ComcactNodeConfig, "algorithm", "bogus"), (ComcactNodeConfig, "qt_targets", "x"),
    (ComcactNodeConfig, "bringup", "both"), (ComcactNodeConfig, "total_steps", 0),
    (ComcactNodeConfig, "eval_episodes", 0), (ComcactNodeConfig, "record_storage", "zip"),
    (ComperNodeConfig, "algorithm", "ddpg"), (ComperNodeConfig, "reducer", "x"),
    (ComperNodeConfig, "total_frames", 0), (ComperNodeConfig, "episode_end", "never"),
    (ComperNodeConfig, "store_every", 0), (ComperNodeConfig, "qt_wait_s", -1.0)])
def test_bad_values_are_refused_with_the_parameter_name(cls, name, bad):
    with pytest.raises(ConfigError, match=f"'{name}'"):
        config_from_dict(cls, {name: bad})


def test_floats_accept_integers_and_strings_are_coerced():
    c = config_from_dict(ComperNodeConfig, {"startup_timeout_s": 60, "qt_wait_s": 1, "record": "true"})
    assert c.startup_timeout_s == 60.0 and isinstance(c.startup_timeout_s, float) and c.record is True


def test_redefault_keeps_description_and_range():
    f = {f.name: f for f in dataclasses.fields(ComperNodeConfig)}
    g = {f.name: f for f in dataclasses.fields(AgentRunConfig)}
    for name in ("qt_wait_s", "progress_period_s"):
        assert f[name].metadata == g[name].metadata and f[name].default != g[name].default
    assert redefault(AgentRunConfig, "keep_checkpoints", 5).metadata["minimum"] == 0


def test_episode_over_rules():
    assert episode_over("standard", True, False) and episode_over("standard", False, True)
    assert not episode_over("truncation_only", True, False) and episode_over("truncation_only", False, True)
    assert episode_over("termination_only", True, False) and not episode_over("termination_only", False, True)


@pytest.mark.parametrize("node_cls, cfg_cls", [(ComcactNode, ComcactNodeConfig), (ComperNode, ComperNodeConfig)])
def test_help_lists_every_node_and_learner_parameter(node_cls, cfg_cls):
    text = help_text(node_cls)
    for f in dataclasses.fields(cfg_cls):
        assert f"\n  {f.name} (default " in text
    assert "\n  num_threads (default 1)" in text and "\n  variant " not in text
    assert "Thesis: 100,000 (chapter 5)" in text or "Thesis: 50,000 (chapter 6)" in text


@pytest.mark.parametrize("module, args, message", [
    ("comcact_node", ["-p", "algorithm:=bogus"], "parameter 'algorithm': 'bogus' is not one of ['comcact', 'ddpg']"),
    ("comper_node", ["-p", "reducer:=x"], "parameter 'reducer': 'x' is not one of"),
    ("comper_node", ["-p", "algorithm:=comper", "-p", "reducer:=memory"], "comper needs QT"),
    ("comper_node", ["-p", "n_step:=3", "-p", "qt_label:=q_sa"], "n_step:=3 needs qt_label:=next_value"),
    ("comcact_node", ["-p", "profile:=best"], "unknown profile 'best'; one of auto, thesis, plain, fresh_labels_gate"),
    ("comcact_node", ["-p", "algorithm:=ddpg", "-p", "profile:=fresh_labels_gate"],
     "profile:=fresh_labels_gate sets COMCACT's value labels and QT step, which ddpg does not have"),
])
def test_a_node_that_cannot_start_says_why_in_one_line_and_exits_1(module, args, message, tmp_path):
    p = subprocess.run([sys.executable, "-m", f"comper_agent.nodes.{module}", "--ros-args", "-p",
                        f"runs_root:={tmp_path}", *args], capture_output=True, text=True, timeout=120)
    out = (p.stdout + p.stderr).strip()
    assert p.returncode == 1, out
    assert len(out.splitlines()) == 1 and "cannot start: " in out and message in out, out
    assert not any(tmp_path.iterdir())          # refused before any run directory is made


def test_recorder_child_exits_when_its_parent_died_before_prctl():
    """PR_SET_PDEATHSIG's race: a parent that died between fork and prctl sends no signal, so the
    child must notice (parent pid changed) and exit instead of running on unowned."""
    from comper_agent.recording.recording_link import _die_with_parent
    cmd = [sys.executable, "-c", "import time; time.sleep(30)"]
    orphan = subprocess.Popen(cmd, preexec_fn=functools.partial(_die_with_parent, os.getpid() + 10_000_000))
    assert orphan.wait(timeout=10) == 1        # "parent" pid differs: exits before exec
    owned = subprocess.Popen(cmd, preexec_fn=functools.partial(_die_with_parent, os.getpid()))
    try:
        with pytest.raises(subprocess.TimeoutExpired):
            owned.wait(timeout=1.0)            # the real parent: it runs
    finally:
        owned.kill()
        owned.wait()


_STUCK_CLOSE = """
import sys, time
from rclpy.node import Node
from comper_msgs_py.ros_main import serve_node
def ready(node):
    print("ready", flush=True)
def close(node):
    print("closing", flush=True)
    time.sleep(600)                            # a close that never ends
sys.exit(serve_node(lambda: Node("stuck_close"), "stuck_close", on_ready=ready, on_close=close, graceful=True,
                    close_timeout_s=3.0))
"""


def test_graceful_node_ignores_repeated_signals_and_a_stuck_close_times_out():
    """serve_node(graceful=True) (the recorder): the first SIGTERM starts the close; repeated ones
    (PR_SET_PDEATHSIG can send several) change nothing; a close that hangs is ended after
    close_timeout_s by faulthandler's watchdog, exit 1, with the stuck stack on stderr."""
    proc = subprocess.Popen([sys.executable, "-c", _STUCK_CLOSE], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True)
    try:
        assert proc.stdout.readline().strip() == "ready"
        start = time.monotonic()
        proc.send_signal(signal.SIGTERM)
        assert proc.stdout.readline().strip() == "closing"      # the first signal is graceful
        proc.send_signal(signal.SIGTERM)
        proc.send_signal(signal.SIGINT)
        with pytest.raises(subprocess.TimeoutExpired):
            proc.wait(timeout=1.0)                              # neither ended it
        assert proc.wait(timeout=15) == 1
        assert time.monotonic() - start >= 2.5
        err = proc.stderr.read()
        assert "Timeout" in err and "in close" in err, err      # the watchdog's dump names the stuck call
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


@pytest.mark.parametrize("node_cls, given, expected", [
    (ComperNode, {"env_id": "CartPole-v1"}, {"reduce_batch": 4_000, "profile": "classic_control"}),
    # the command line still wins
    (ComperNode, {"env_id": "CartPole-v1", "reduce_batch": 1_500}, {"reduce_batch": 1_500}),
    (ComperNode, {"env_id": "ALE/Freeway-v5"}, {"reduce_batch": 4_000, "n_step": 10, "profile": "atari_100k"}),
    (ComperNode, {"env_id": "ALE/Freeway-v5", "profile": "thesis"}, {"reduce_batch": 1_000, "n_step": 1}),  # Table 34
    (ComcactNode, {}, {"restore_batch": True, "label_critic": "target", "qt_step_gate": True,
                       "profile": "fresh_labels_gate"}),
    (ComcactNode, {"algorithm": "ddpg"}, {"restore_batch": False, "batch_norm": False, "profile": "plain"}),
    (ComcactNode, {"profile": "thesis"}, {"restore_batch": False, "label_critic": "online", "qt_step_gate": False,
                                          "batch_norm": True, "store_every": 1, "reduce_every": 1}),
    (ComcactNode, {}, {"batch_norm": False, "store_every": 10, "reduce_every": 10}),
    (ComcactNode, {"label_critic": "online"}, {"restore_batch": True, "label_critic": "online", "qt_step_gate": True}),
])
def test_a_profile_sets_node_and_learner_parameters_and_the_command_line_still_wins(node_cls, given, expected):
    """What a learner node's start does with a profile (harness.declare_learner_parameters), without the
    bring-up: node parameters first (algorithm, env_id and profile before the others), then the learner's with
    the profile's values as defaults."""
    import rclpy
    from rclpy.parameter import Parameter

    from comper_msgs_py.params import config_to_dict
    from comper_agent.nodes.harness import declare_learner_parameters
    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    try:
        node = rclpy.create_node("profile_probe", context=ctx, parameter_overrides=[
            Parameter(k, value=v) for k, v in given.items()])
        p, cfg, profile = declare_learner_parameters(node, node_cls)
        got = {**config_to_dict(p), **config_to_dict(cfg), "profile": profile}
        assert {k: got[k] for k in expected} == expected
        node.destroy_node()
    finally:
        ctx.try_shutdown()


def test_reduce_batch_pace_rule():
    from comper_agent.core.memory_schedule import sets_touched_per_reduction
    assert sets_touched_per_reduction(100, 32, 4, True) == 900 <= 1_000        # the thesis's Atari settings keep pace
    assert sets_touched_per_reduction(100, 64, 2, True) == 3_300 > 1_000       # classic_control's pace
    assert sets_touched_per_reduction(100, 64, 2, False) == 100


def test_resume_names_the_parameters_that_differ_from_the_checkpoint():
    from comper_agent.nodes.agent_run import changed_parameters
    saved = {"params": {"profile": "fresh_labels_gate", "restore_batch": True, "total_steps": 200, "resume": ""},
             "learner": {"qt_step_gate": True, "actor_hidden": [400, 300], "seed": 0}}
    now = {"params": {"profile": "thesis", "restore_batch": False, "total_steps": 300, "resume": "runs/x",
                      "new_param": 1},
           "learner": {"qt_step_gate": False, "actor_hidden": (400, 300), "seed": 0}}
    # what a resume is for (how far, from where) is not named; a parameter the checkpoint lacks is not either
    assert changed_parameters(saved, now) == ["profile 'fresh_labels_gate' -> 'thesis'", "restore_batch True -> False",
                                              "qt_step_gate True -> False"]
    assert changed_parameters({}, now) == [] and changed_parameters(saved, saved) == []


def _returns_within(fn, seconds: float = 5.0) -> bool:
    """Runs fn in a helper thread; whether it returned within `seconds` (a deadlocked fn never does)."""
    t = threading.Thread(target=fn, daemon=True)
    t.start()
    t.join(seconds)
    return not t.is_alive()


def test_the_learners_stop_handler_takes_no_lock_and_a_second_signal_aborts():
    """A signal handler runs in the main thread, possibly inside Event.set / Event.wait with the event's lock
    held (a second SIGTERM inside the first one's handler did that: the learner hung for ever). With both locks
    held, StopRequests.handler still returns, the stop arrives once they are free, and a second signal raises
    KeyboardInterrupt (abort)."""
    node_stop, requests = threading.Event(), []
    stops = StopRequests(lambda: (requests.append(1), node_stop.set()))
    try:
        with stops.stop._cond, node_stop._cond:
            assert _returns_within(lambda: stops.handler(signal.SIGTERM, None))
        assert node_stop.wait(5.0) and stops.stop.is_set() and requests == [1]
        with pytest.raises(KeyboardInterrupt):
            stops.handler(signal.SIGTERM, None)
        time.sleep(0.1)
        assert requests == [1]
    finally:
        stops.close()


def test_the_supervisors_signal_handler_takes_no_lock():
    """The same for bringup's supervisor: its handler only counts, the loops read the count."""
    sup = Supervisor([], stop_timeout=1.0, ready_timeout=1.0, out=io.StringIO())
    with sup.wake._cond:
        assert _returns_within(lambda: sup.on_signal(signal.SIGINT, None))
    assert sup.signals == 1


def test_the_embedded_memory_samples_from_the_run_seed_unless_told_otherwise():
    """A lock-step run repeats for a fixed seed: the embedded memory's sampling generator is seeded by it; a
    sample_seed on the command line (-1: OS entropy) or from the learner wins."""
    from comper_agent.nodes.bringup import seeded_sampling
    assert seeded_sampling({"snapshot_root": "x"}, 7, {}) == {"sample_seed": 7, "snapshot_root": "x"}
    assert seeded_sampling({}, 7, {"sample_seed": object()}) == {}
    assert seeded_sampling({"sample_seed": 3}, 7, {}) == {"sample_seed": 3}

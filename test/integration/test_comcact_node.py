"""comcact_node end to end over real ROS 2 (separate processes, no mocks):
embedded bring-up on InvertedPendulum-v4 (evaluations and episodes published, run directory
written, Ctrl-C saves a final checkpoint); external bring-up with sim_node, memory_node and
qt_trainer_node started by ros2 run (with profile fresh_labels_gate: its values reach node and learner,
and with restore_batch the re-stored batches join their sets in the memory node); the ddpg variant with a checkpoint round trip and resume (the replay buffer's contents saved and
restored)."""
import json
import math
import os
import signal
import time

import pytest
import torch
import yaml

from comper_agent.nodes import run_io
from comper_agent.nodes.comcact_node import SUMMARY_QOS
from comper_msgs.msg import EpisodeSummary, EvaluationResult
from conftest import spin_once
from scaffolding import load_benchmark

TASK = "InvertedPendulum-v4"


def _args(tmp_path, run_id, *extra):
    return ["--ros-args", "-p", f"env_id:={TASK}", "-p", f"runs_root:={tmp_path}", "-p", f"run_id:={run_id}",
            "-p", "progress_period_s:=1.0", "-p", "transport_probe_calls:=10", "-p", "tensorboard:=false",
            *extra]


def _wait(proc, timeout):
    try:
        return proc.proc.wait(timeout=timeout)
    except Exception:
        raise AssertionError(f"{proc.name} did not finish within {timeout} s:\n{proc.log()[-4000:]}")


def _evals(tmp_path, run_id):
    return [r["step"] for r in run_io.MetricsLog.read(tmp_path / run_id / "metrics.jsonl", "eval")]


def test_embedded_bringup_trains_publishes_and_stops_cleanly_on_ctrl_c(launch, ros_node, tmp_path):
    name = f"comcact_{os.getpid()}"
    evals, episodes = [], []
    ros_node.create_subscription(EvaluationResult, f"/{name}/evaluations", evals.append, SUMMARY_QOS)
    ros_node.create_subscription(EpisodeSummary, f"/{name}/episodes", episodes.append, SUMMARY_QOS)
    proc = launch("comper_agent", "comcact_node",
                  *_args(tmp_path, "emb", "-p", "total_steps:=100000", "-p", "eval_every:=150",
                         "-p", "eval_episodes:=2", "-p", "reduce_every:=5", "-p", "diagnostics_every:=20"),
                  "-r", f"comcact_node:__node:={name}", name=name)
    deadline = time.monotonic() + 180
    while time.monotonic() < deadline and proc.alive():
        spin_once(ros_node, 0.2)
        # both topics are volatile and each is matched on its own: on a loaded machine ~/episodes can be matched
        # after the evaluations at steps 150 and 300 went out, so wait for an evaluation's episodes too
        if any(e.global_step >= 300 for e in evals) and any(x.source == "eval" for x in episodes):
            break
    assert any(e.global_step >= 300 for e in evals), f"no evaluation at step 300:\n{proc.log()[-4000:]}"
    os.killpg(proc.proc.pid, signal.SIGINT)
    assert _wait(proc, 60) == 0, proc.log()[-4000:]
    log = proc.log()
    assert "COMCACT (memory + QT step) on InvertedPendulum-v4" in log and "embedded bring-up" in log
    assert "steps/s" in log and "ETA" in log and "time split" in log and "final checkpoint" in log

    e = evals[0]
    assert e.algorithm == "comcact" and e.env_id == TASK and e.run_id == "emb" and len(e.episode_returns) == 2
    # the run's own record has every evaluation; the topic is volatile, so a subscriber whose discovery finishes
    # after the step-0 evaluation (a loaded machine) misses that one, and gets the later ones in order
    recorded = _evals(tmp_path, "emb")
    assert recorded[:3] == [0, 150, 300]
    published = [x.global_step for x in evals]
    assert 300 in published and published == sorted(published) and set(published) <= set(recorded)
    assert {x.source for x in episodes} == {"train", "eval"}
    run = tmp_path / "emb"
    assert {"config.yaml", "metrics.jsonl", "progress.csv", "checkpoints"} <= {p.name for p in run.iterdir()}
    state = torch.load(run / "checkpoints" / "latest.pt", weights_only=True)["state"]
    assert state["counters"]["step"] >= 300
    assert state["qt_trainer"]["qt"]["version"] >= 1         # QT trained and checkpointed
    assert set(state["learner"]) >= {"actor", "critic", "actor_target", "critic_target", "actor_opt",
                                     "critic_opt", "noise"}
    timers = run_io.MetricsLog.read(run / "metrics.jsonl", "timers")[-1]
    assert {"sim", "memory", "qt", "learner"} <= set(timers["phases"])
    diag = run_io.MetricsLog.read(run / "metrics.jsonl", "qt_diagnostics")   # every 20 updates once QT exists
    assert diag and all(d["update"] % 20 == 0 and d["qt_version"] >= 1 for d in diag)
    for d in diag:
        assert d["qt_target_rmse"] >= 0 and d["critic_td_rmse"] >= 0 and d["set_size_mean"] >= 1
        assert 0 <= d["multi_member_fraction"] <= 1 and 0 <= d["label_age_mean"] <= d["step"]
    progress = [r for r in run_io.MetricsLog.read(run / "metrics.jsonl", "progress") if "qt_steps_taken" in r]
    assert progress, "progress records carry the QT step counts"
    last = progress[-1]    # the default gates: every update after QT's first version took its QT step or was gated
    assert 0 < last["qt_steps_taken"] + last["qt_steps_gated"] <= last["learner_updates"]
    assert "profile fresh_labels_gate (profile:=thesis is the thesis); differs from it in" in log


def test_external_bringup_uses_nodes_started_with_ros2_run(launch, tmp_path):
    tag = os.getpid()
    sim, mem, qt = f"sim_x{tag}", f"mem_x{tag}", f"qt_x{tag}"
    launch("comper_sim", "sim_node", "--ros-args", "-p", f"env_id:={TASK}", "-r", f"__node:={sim}", name=sim)
    launch("comper_memory", "memory_node", "--ros-args", "-r", f"__node:={mem}", name=mem)
    launch("comper_agent", "qt_trainer_node", "--ros-args", "-p", f"memory_node:={mem}", "-r", f"__node:={qt}",
           name=qt)
    proc = launch("comper_agent", "comcact_node",
                  *_args(tmp_path, "ext", "-p", "bringup:=external", "-p", f"sim_node:={sim}",
                         "-p", f"memory_node:={mem}", "-p", f"qt_trainer_node:={qt}", "-p", "total_steps:=200",
                         "-p", "eval_every:=100", "-p", "eval_episodes:=1", "-p", "startup_timeout_s:=60",
                         "-p", "profile:=fresh_labels_gate", "-p", "diagnostics_every:=10"),
                  name="learner_ext")
    assert _wait(proc, 240) == 0, proc.log()[-4000:]
    assert "external bring-up" in proc.log() and "profile fresh_labels_gate" in proc.log()
    # the profile set node and learner parameters alike, and config.yaml says where each value came from
    cfg = yaml.safe_load((tmp_path / "ext" / "config.yaml").read_text())
    assert cfg["params"]["restore_batch"] is True and cfg["params"]["profile"] == "fresh_labels_gate"
    assert cfg["learner"]["label_critic"] == "target" and cfg["learner"]["qt_step_gate"] is True
    assert cfg["profile"]["name"] == "fresh_labels_gate" and "docs/studies/comcact-qt-step-gate.md" in \
        cfg["profile"]["values"]["qt_step_gate"]["source"]
    assert _evals(tmp_path, "ext") == [0, 100, 200]
    state = torch.load(tmp_path / "ext" / "checkpoints" / "latest.pt", weights_only=True)["state"]
    assert state["counters"]["step"] == 200 and state["counters"]["reductions"] >= 1
    # a memory node without snapshot_root refuses the checkpoint's snapshot: said once, weights still saved
    assert proc.log().count("checkpoints hold no memory contents") == 1 and "replay" not in state
    # restore_batch: every updated batch went back to the memory node and joined its transitions' sets
    diag = run_io.MetricsLog.read(tmp_path / "ext" / "metrics.jsonl", "qt_diagnostics")
    assert len(diag) > 3 and diag[-1]["restored"] > diag[0]["restored"] >= 0
    assert max(d["multi_member_fraction"] for d in diag) > 0.5 and diag[-1]["set_size_mean"] > 2


def test_ddpg_variant_checkpoint_and_resume_continue_the_step_count(launch, tmp_path):
    common = ["-p", "algorithm:=ddpg", "-p", "eval_every:=100", "-p", "eval_episodes:=1"]
    first = launch("comper_agent", "comcact_node", *_args(tmp_path, "dd", *common, "-p", "total_steps:=200",
                                                            "-p", "warmup_steps:=100"), name="ddpg1")
    assert _wait(first, 240) == 0, first.log()[-4000:]
    assert "DDPG baseline" in first.log()
    ck = tmp_path / "dd" / "checkpoints" / "latest.pt"
    s1 = torch.load(ck, weights_only=True)["state"]
    assert s1["counters"]["step"] == 200 and s1["run"]["algorithm"] == "ddpg" and "qt_trainer" not in s1
    # the replay buffer's contents are saved beside the checkpoint (checkpoint_replay, default on)
    assert s1["replay"]["kind"] == "local" and s1["replay"]["transitions"] == 200
    assert (ck.parent / s1["replay"]["file"]).is_file() and s1["replay"]["file"] == "step_000000200.replay.npz"

    second = launch("comper_agent", "comcact_node",
                    "--ros-args", "-p", f"env_id:={TASK}", "-p", f"resume:={tmp_path / 'dd'}", *common,
                    "-p", "total_steps:=300", "-p", "transport_probe_calls:=0", "-p", "tensorboard:=false",
                    name="ddpg2")
    assert _wait(second, 240) == 0, second.log()[-4000:]
    assert "resuming at step 200" in second.log()
    assert "replay buffer restored from" in second.log() and ": 200 transitions" in second.log()
    # what the second command left out (warm-up, console settings) is named, and its values apply
    changed = [ln for ln in second.log().splitlines() if "differ from the checkpoint's" in ln]
    assert len(changed) == 1 and "warmup_steps 100 -> 0" in changed[0] and "total_steps" not in changed[0], changed
    s2 = torch.load(ck, weights_only=True)["state"]
    assert s2["counters"]["step"] == 300 and s2["learner"]["updates"] > s1["learner"]["updates"]
    assert s2["counters"]["episodes"] > s1["counters"]["episodes"]
    assert _evals(tmp_path, "dd") == [0, 100, 200, 300]          # appended in the same run directory

    # the actor's saturation offline, on the states of the checkpoint's replay (benchmarks/actor_saturation.py)
    row = load_benchmark("actor_saturation").saturation(tmp_path / "dd", max_states=1000, seed=0, actor_steps=20)
    assert row["algorithm"] == "ddpg" and row["step"] == 300 and row["states"] == 300
    assert 0.0 <= row["all_saturated"] <= row["saturation"] <= 1.0 and row["mean_abs_x"] > 0.0
    assert row["action_spread"] > 0.0          # 300 updates in, the actor still answers states differently
    assert row["actor_steps"] == 20 and 0.0 <= row["after_saturation"] <= 1.0
    assert all(map(math.isfinite, (row["q_before"], row["q_after"])))

    # a checkpoint whose replay file has gone: the resume stops at start with one readable error, writing nothing
    (ck.parent / s2["replay"]["file"]).unlink()
    third = launch("comper_agent", "comcact_node",
                   "--ros-args", "-p", f"env_id:={TASK}", "-p", f"resume:={tmp_path / 'dd'}", *common,
                   "-p", "total_steps:=400", "-p", "transport_probe_calls:=0", "-p", "tensorboard:=false",
                   name="ddpg3")
    assert _wait(third, 120) == 1, third.log()[-4000:]
    assert "cannot resume: cannot restore the replay buffer" in third.log() and "checkpoint_replay:=false" in third.log()
    assert _evals(tmp_path, "dd") == [0, 100, 200, 300]
    assert torch.load(ck, weights_only=True)["state"]["counters"]["step"] == 300


@pytest.mark.parametrize("where", ["child", "in_process"])
def test_record_parameter_writes_a_bag_that_reproduces_the_training_returns(launch, tmp_path, where):
    """record:=true: the recorder (a child process by default, or in-process) bags the run; the bag's
    episode returns equal those the node logged, every training episode's transitions are in it,
    and evaluate reads it."""
    from comper_agent.offline import runs as offline

    proc = launch("comper_agent", "comcact_node",
                  *_args(tmp_path, "rec", "-p", "algorithm:=ddpg", "-p", "total_steps:=400", "-p", "warmup_steps:=150",
                         "-p", "eval_every:=200", "-p", "eval_episodes:=2", "-p", "record:=true",
                         "-p", f"record_process:={where}", "-p", "transport_probe_calls:=0"), name="rec")
    assert _wait(proc, 240) == 0, proc.log()[-4000:]
    if where == "child":
        rec_log = (tmp_path / "rec" / "recorder.log").read_text()
        assert "bag closed" in rec_log and "Traceback" not in rec_log, rec_log
    logged = [(r["episode"], r["ret"], r["length"])
              for r in run_io.MetricsLog.read(tmp_path / "rec" / "metrics.jsonl", "episode") if r["source"] == "train"]
    assert len(logged) >= 3
    runs = offline.read_runs([tmp_path / "rec"])
    (run,) = runs.values()
    bagged = [(e.episode_id, e.episode_return, e.length) for e in run.train_episodes()]
    assert bagged == logged                                     # exact float64 equality
    check = offline.cross_check(run)
    assert check["checked"] == len(logged) and not check["mismatches"] and check["missing"] == 0
    assert [p.global_step for p in run.evaluations] == [0, 200, 400]


@pytest.mark.parametrize("where", ["child", "in_process"])
def test_record_keeps_every_episode_when_the_agent_outpaces_the_recorder(launch, tmp_path, where):
    """Random-action InvertedPendulum episodes (a few steps each, hundreds per second) come faster than
    the recorder writes them: the agent waits at record_window unwritten episodes (RecordingFlow), so
    the topics' KEEP_LAST 100 queues drop none (before the flow control, 27 % went missing). The
    in-process run also records without compression (record_compression:=none reaches the recorder)."""
    from comper_agent.offline import runs as offline

    compression = "zstd" if where == "child" else "none"
    proc = launch("comper_agent", "comcact_node",
                  *_args(tmp_path, "fast", "-p", "algorithm:=ddpg", "-p", "total_steps:=6000", "-p", "warmup_steps:=6000",
                         "-p", "eval_every:=0", "-p", "record:=true", "-p", f"record_process:={where}",
                         "-p", f"record_compression:={compression}", "-p", "transport_probe_calls:=0"), name="fast")
    assert _wait(proc, 240) == 0, proc.log()[-4000:]
    assert "written off" not in proc.log()
    logged = [(r["episode"], r["ret"], r["length"])
              for r in run_io.MetricsLog.read(tmp_path / "fast" / "metrics.jsonl", "episode") if r["source"] == "train"]
    (run,) = offline.read_runs([tmp_path / "fast"]).values()
    assert len(logged) > 300
    assert [(e.episode_id, e.episode_return, e.length) for e in run.train_episodes()] == logged
    (meta,) = (tmp_path / "fast").rglob("metadata.yaml")
    custom = yaml.safe_load(meta.read_text())["rosbag2_bagfile_information"]["custom_data"]
    assert json.loads(custom["recorder"])["compression"] == compression


def test_agent_goes_on_without_waiting_when_its_recorder_process_dies(launch, tmp_path):
    """A SIGKILLed recorder process: the agent says so once, stops the flow control (no record_wait_s
    stalls) and finishes the run."""
    proc = launch("comper_agent", "comcact_node",
                  *_args(tmp_path, "norec", "-p", "algorithm:=ddpg", "-p", "total_steps:=30000",
                         "-p", "warmup_steps:=30000", "-p", "eval_every:=0", "-p", "record:=true",
                         "-p", "record_wait_s:=600.0", "-p", "transport_probe_calls:=0"), name="norec")
    deadline = time.monotonic() + 60
    while "recorder process (pid " not in proc.log() and time.monotonic() < deadline:
        assert proc.proc.poll() is None, proc.log()[-4000:]
        time.sleep(0.1)
    os.kill(int(proc.log().split("recorder process (pid ")[1].split(",")[0]), signal.SIGKILL)
    assert _wait(proc, 120) == 0, proc.log()[-4000:]
    log = proc.log()
    assert log.count("this run is no longer recorded") == 1 and "written off" not in log, log[-4000:]


def test_sigkill_of_the_agent_leaves_a_closed_bag_with_every_logged_episode(launch, tmp_path):
    """record_process:=child: SIGKILL of the agent makes the kernel send SIGTERM to the recorder
    process (PR_SET_PDEATHSIG), which writes what it holds and closes the bag."""
    from comper_agent.offline import runs as offline

    proc = launch("comper_agent", "comcact_node",
                  *_args(tmp_path, "killed", "-p", "algorithm:=ddpg", "-p", "total_steps:=100000",
                         "-p", "warmup_steps:=100000", "-p", "eval_every:=0", "-p", "record:=true"), name="killed")
    metrics = tmp_path / "killed" / "metrics.jsonl"
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline:
        if metrics.exists() and len(run_io.MetricsLog.read(metrics, "episode")) >= 30:
            break
        assert proc.proc.poll() is None, proc.log()[-4000:]
        time.sleep(0.5)
    log = proc.log()
    pid = int(log.split("recorder process (pid ")[1].split(",")[0])
    proc.proc.send_signal(signal.SIGKILL)
    proc.proc.wait(timeout=10)
    deadline = time.monotonic() + 30
    while time.monotonic() < deadline and os.path.exists(f"/proc/{pid}") and \
            open(f"/proc/{pid}/stat").read().split()[2] != "Z":
        time.sleep(0.2)
    rec_log = (tmp_path / "killed" / "recorder.log").read_text()
    assert "bag closed" in rec_log, rec_log
    logged = [(r["episode"], r["ret"], r["length"])
              for r in run_io.MetricsLog.read(metrics, "episode") if r["source"] == "train"]
    (run,) = offline.read_runs([tmp_path / "killed"]).values()
    bagged = [(e.episode_id, e.episode_return, e.length) for e in run.train_episodes()]
    # every episode the agent logged (it logs after publishing) is in the bag, bar one in flight at the kill
    assert len(logged) >= 30 and bagged[:len(logged) - 1] == logged[:-1]


def test_reduce_overlap_reduces_while_learning(launch, tmp_path):
    """reduce_overlap:=true: the reductions are sent and collected while the learner goes on; every
    one is collected (none left in flight at the end), QT is trained and checkpointed."""
    proc = launch("comper_agent", "comcact_node",
                  *_args(tmp_path, "ov", "-p", "total_steps:=400", "-p", "eval_every:=0", "-p", "reduce_every:=5",
                         "-p", "reduce_overlap:=true"), name="ov")
    assert _wait(proc, 240) == 0, proc.log()[-4000:]
    run = tmp_path / "ov"
    state = torch.load(run / "checkpoints" / "latest.pt", weights_only=True)["state"]
    ph = run_io.MetricsLog.read(run / "metrics.jsonl", "timers")[-1]["phases"]
    # the first reduction (RTM empty) is synchronous ('qt'); the rest were overlapped and collected
    assert ph["qt"]["calls"] == 1
    collected = ph.get("reduce_collect", {"calls": 0})["calls"] + ph.get("reduce_wait", {"calls": 0})["calls"]
    assert collected >= 30 and state["counters"]["reductions"] == collected + 1
    assert state["qt_trainer"]["qt"]["version"] >= collected
    assert state["learner"]["qt_steps"] > 0

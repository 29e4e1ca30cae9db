"""comper_node end to end over real ROS 2 (separate processes, no mocks), ALE/Freeway-v5, embedded bring-up.

* COMPER: episodes cut at 1,000 frames by the embedded sim (``max_episode_frames``) so a few hundred
  steps hold whole episodes; ~/episodes and ~/transitions received by this test: uint8 84x84 frames,
  18 actions, frames = 5 x steps (skipped frames counted), labels stored; sticky actions 0.25 in the
  run's env spec; summary.json with the protocol figures; checkpoint (with the memory node's snapshot),
  then resume restores the memory and continues the step count, frames and episode list (going back past a
  final checkpoint that a failed service left without the memory).
* comper_f, comper_m, dqn in parallel (distinct node names): each runs 300 steps and uses the
  sampling source / target / reducer it should (summary.json, checkpoint contents, phase timers).
* record:=true (dqn, 300 steps): the in-process recorder's bag holds every episode and its transitions.
"""
import json
import os
import time

import pytest
import numpy as np
import torch
import yaml

from comper_agent.nodes import run_io
from comper_agent.nodes.comper_node import SUMMARY_QOS, TRANSITIONS_QOS
from comper_msgs.msg import EpisodeSummary, TransitionBatch
from comper_msgs_py.convert import batch_to_transitions
from conftest import spin_once
from scaffolding import load_benchmark

GAME = "ALE/Freeway-v5"


def _args(tmp_path, run_id, tag, *extra, profile: str | None = "thesis"):
    """The ALE runs take the thesis profile (single frames, updates from step 100: the pipeline in a few hundred
    steps; the default on ALE, atari_100k, starts learning at 1,600); profile None: the node's own choice."""
    return ["--ros-args", "-p", f"env_id:={GAME}", "-p", f"runs_root:={tmp_path}", "-p", f"run_id:={run_id}",
            "-p", "progress_period_s:=2.0", "-p", "transport_probe_calls:=10", "-p", "tensorboard:=false",
            "-p", f"sim_node:=sim_{tag}", "-p", f"memory_node:=mem_{tag}", "-p", f"qt_trainer_node:=qt_{tag}",
            *(["-p", f"profile:={profile}"] if profile else []), *extra]


def _wait(proc, timeout):
    try:
        return proc.proc.wait(timeout=timeout)
    except Exception:
        raise AssertionError(f"{proc.name} did not finish within {timeout} s:\n{proc.log()[-4000:]}")


def _state(run):
    return torch.load(run / "checkpoints" / "latest.pt", weights_only=True)["state"]


def test_comper_publishes_episodes_and_transitions_summary_checkpoint_and_resume(launch, ros_node, tmp_path):
    tag = f"c{os.getpid()}"
    name = f"comper_{tag}"
    episodes, batches = [], []
    ros_node.create_subscription(EpisodeSummary, f"/{name}/episodes", episodes.append, SUMMARY_QOS)
    ros_node.create_subscription(TransitionBatch, f"/{name}/transitions", batches.append, TRANSITIONS_QOS)
    common = ["-p", "max_episode_frames:=1000", "-p", "checkpoint_every:=0"]
    proc = launch("comper_agent", "comper_node", *_args(tmp_path, "cr", tag, *common, "-p", "max_steps:=420"),
                  "-r", f"comper_node:__node:={name}", name=name)
    deadline = time.monotonic() + 240      # generous: the machine may be shared (~60 s alone)
    while time.monotonic() < deadline and proc.alive():
        spin_once(ros_node, 0.2)
    assert _wait(proc, 30) == 0, proc.log()[-4000:]
    deadline = time.monotonic() + 10       # messages already delivered, not yet taken
    while time.monotonic() < deadline and (len(batches) < 2 or sum(e.source == "train" for e in episodes) < 2):
        spin_once(ros_node, 0.05)
    log = proc.log()
    assert "COMPER (RTM sampling, QT target) on ALE/Freeway-v5" in log and "embedded bring-up" in log
    assert "time split" in log and "final checkpoint" in log and "mean of the last" in log

    # episodes: 1,000-frame cut = 200 agent steps at frame skip 5; frames counted with skipped ones
    train = [e for e in episodes if e.source == "train"]
    assert len(train) == 2, [(e.length, e.frames) for e in train]
    assert all(e.frames == 1000 and e.length == 200 and e.truncated for e in train)
    assert [e.global_frames for e in train] == [1000, 2000] and [e.global_step for e in train] == [200, 400]
    # transitions of each episode, with the labels that were stored
    assert len(batches) == 2
    t = batch_to_transitions(batches[0])
    assert len(t) == 200 and t.states.dtype == np.uint8 and t.states.shape == (200, 84, 84)
    assert t.next_states.shape == (200, 84, 84) and np.array_equal(t.states[1:], t.next_states[:-1])
    assert t.actions.min() >= 0 and t.actions.max() < 18 and np.all(t.actions == np.round(t.actions))
    assert t.value_labels.shape == (200,) and np.isfinite(t.value_labels).all()
    assert list(t.steps) == list(range(200))

    run = tmp_path / "cr"
    cfg = yaml.safe_load((run / "config.yaml").read_text())
    spec = cfg["env"]["spec"]
    assert cfg["env"]["frame_skip"] == 5 and cfg["env"]["observation_shape"] == [84, 84]
    assert abs(float(spec["repeat_action_probability"]) - 0.25) < 1e-9, spec          # sticky actions on
    s = json.loads((run / "summary.json").read_text())
    assert s["steps"] == 420 and s["frames"] == 2100 and len(s["episode_returns"]) == 2
    assert s["protocol"]["last_k"] == 2 and s["protocol"]["tercile_k"] == 3 and len(s["protocol"]["terciles"]) == 3
    assert s["sampling"]["source"] == "rtm" and s["sampling"]["target"] == "qt" and s["sampling"]["restored"] > 0
    assert s["reductions"] >= 4 and s["updates"] >= 75 and s["memory"]["rtm_size"] > 0
    st = _state(run)
    assert st["counters"]["step"] == 420 and st["qt_trainer"]["qt"]["version"] >= 4
    assert "q_target" not in st["learner"]
    assert {"sim", "memory", "qt", "learner", "qt_predict"} <= set(run_io.MetricsLog.read(
        run / "metrics.jsonl", "timers")[-1]["phases"])
    saved = run_io.MetricsLog.read(run / "metrics.jsonl", "memory")     # the last one: at the final checkpoint
    assert saved and saved[-1]["identities"] > 0

    # a later start that failed (its memory node did not answer) left a final checkpoint of weights and counters
    # only on top (what the harness writes then, run_io.REPLAY_SKIPPED): the resume goes back past it to step 420
    failed = {k: v for k, v in st.items() if k != "replay"}
    failed.update(counters={**st["counters"], "step": 421}, **{run_io.REPLAY_SKIPPED: "a service failed"})
    run_io.RunDir(tmp_path, "cr").save_checkpoint(failed, 421)

    # resume: continues step, frames, episodes and updates in the same run directory
    second = launch("comper_agent", "comper_node",
                    *_args(tmp_path, "ignored", tag, *common, "-p", f"resume:={run}", "-p", "max_steps:=620"),
                    name="comper_resume")
    assert _wait(second, 150) == 0, second.log()[-4000:]
    assert "resuming at step 420" in second.log()
    assert "latest.pt (step 421) holds no memory / replay contents (a service failed); continuing from " \
           "step_000000420.pt" in second.log(), second.log()[-3000:]
    # the memory node's state went into the checkpoint and came back before the resumed run stored anything
    assert st["replay"]["kind"] == "memory" and (run / "checkpoints" / "step_000000420.memory").is_dir()
    restored = [ln for ln in second.log().splitlines() if "memory restored from" in ln]
    assert len(restored) == 1, second.log()[-3000:]
    # (TM sets may be more: the checkpoint first stores the re-stored batch waiting, which reopens its sets)
    assert f": {saved[-1]['identities']} identities, TM sets " in restored[0], (restored, saved[-1])
    assert restored[0].endswith(f"RTM {saved[-1]['rtm_size']}"), (restored, saved[-1])
    st2 = _state(run)
    assert st2["counters"]["step"] == 620 and st2["counters"]["frames"] == 3100
    assert st2["learner"]["updates"] > st["learner"]["updates"]
    assert st2["returns"][:2] == st["returns"] and len(st2["returns"]) == 2 + 1   # new episode after resume
    assert not (tmp_path / "ignored").exists()


def test_variants_use_their_sampling_source_and_target(launch, tmp_path):
    runs = {}
    for alg in ("comper_f", "comper_m", "dqn"):
        extra = ["-p", f"algorithm:={alg}", "-p", "max_steps:=300", "-p", "checkpoint_every:=0"]
        if alg == "dqn":   # the baseline starts learning at 1,000 steps (Table 35): earlier here, small replay
            extra += ["-p", "learning_starts:=100", "-p", "replay_size:=2000", "-p", "target_update_every:=100"]
        if alg == "comper_m":   # the target copy's bootstrap where QT's is off by more than its spread
            extra += ["-p", "target_update_every:=100", "-p", "qt_target_gate:=true"]
        runs[alg] = launch("comper_agent", "comper_node", *_args(tmp_path, alg, f"{alg}{os.getpid()}", *extra),
                           name=alg)
    for alg, proc in runs.items():
        assert _wait(proc, 170) == 0, proc.log()[-4000:]
    s = {alg: json.loads((tmp_path / alg / "summary.json").read_text()) for alg in runs}
    st = {alg: _state(tmp_path / alg) for alg in runs}
    ph = {alg: set(run_io.MetricsLog.read(tmp_path / alg / "metrics.jsonl", "timers")[-1]["phases"]) for alg in runs}

    # COMPER-F: RTM sampling, DQN target network, reduction by the memory (no QT trained)
    assert "COMPER-F" in runs["comper_f"].log()
    assert s["comper_f"]["sampling"] == {**s["comper_f"]["sampling"], "source": "rtm", "target": "target_network",
                                         "reducer": "memory"}
    assert "q_target" in st["comper_f"]["learner"] and "qt_trainer" not in st["comper_f"]
    assert "memory_reduce" in ph["comper_f"] and "qt" not in ph["comper_f"] and "qt_predict" not in ph["comper_f"]
    assert s["comper_f"]["updates"] >= 45 and s["comper_f"]["memory"]["rtm_size"] > 0
    # RTM sampling: the batches of the updates up to the next reduction come in one call (25 per 100 steps)
    assert s["comper_f"]["sampling"]["sample_calls"] * 10 <= s["comper_f"]["updates"]

    # COMPER-M: QT target, sampling from TM, QT trained by the QT trainer; with qt_target_gate a target copy is
    # kept (and checkpointed) for the gate's fallback; the gate's count is reported and checkpointed
    assert s["comper_m"]["sampling"]["source"] == "tm" and s["comper_m"]["sampling"]["target"] == "qt"
    assert s["comper_m"]["sampling"]["sample_calls"] >= 40     # TM changes every step: one call per update
    assert "q_target" in st["comper_m"]["learner"] and st["comper_m"]["qt_trainer"]["qt"]["version"] >= 2
    assert "target network every 100 steps" in runs["comper_m"].log()
    assert "qt_target_gate: QT's or the target network's bootstrap per batch" in runs["comper_m"].log()
    gated = s["comper_m"]["sampling"]["qt_gated"]
    assert 0 <= gated <= s["comper_m"]["updates"] and "qt_gated" not in s["comper_f"]["sampling"]
    assert "qt_gated" in st["comper_m"]["learner"]
    shares = [r["qt_gated_share"] for r in run_io.MetricsLog.read(tmp_path / "comper_m" / "metrics.jsonl", "progress")
              if "qt_gated_share" in r]
    assert shares and all(0.0 <= x <= 1.0 for x in shares)
    assert {"qt", "qt_predict"} <= ph["comper_m"]

    # DQN: in-process replay (4 stacked frames), target network, no memory or QT nodes
    assert "DQN baseline" in runs["dqn"].log() and "obs [4, 84, 84]" in runs["dqn"].log()
    assert s["dqn"]["sampling"]["source"] == "replay" and s["dqn"]["frame_stack"] == 4
    assert "q_target" in st["dqn"]["learner"] and "qt_trainer" not in st["dqn"]
    assert "memory" not in ph["dqn"] and "qt" not in ph["dqn"] and s["dqn"]["updates"] >= 45
    assert s["dqn"]["memory"]["replay_size"] == 300


def test_record_parameter_bags_the_run_with_every_episode_and_its_transitions(launch, tmp_path):
    """record:=true (shared with comcact_node): the in-process recorder bags ~/transitions and
    ~/episodes; the bag's returns equal the logged ones and every episode's transitions are in it
    (dqn: the cheapest variant; its transitions carry no labels)."""
    from comper_agent.offline import runs as offline

    tag = f"r{os.getpid()}"
    proc = launch("comper_agent", "comper_node",
                  *_args(tmp_path, "rec", tag, "-p", "algorithm:=dqn", "-p", "max_steps:=300",
                         "-p", "max_episode_frames:=500", "-p", "learning_starts:=100", "-p", "replay_size:=2000",
                         "-p", "record:=true", "-p", "transport_probe_calls:=0"), name="rec")
    assert _wait(proc, 170) == 0, proc.log()[-4000:]
    logged = [(r["episode"], r["ret"], r["length"])
              for r in run_io.MetricsLog.read(tmp_path / "rec" / "metrics.jsonl", "episode")]
    assert len(logged) == 3
    (run,) = offline.read_runs([tmp_path / "rec"]).values()
    assert [(e.episode_id, e.episode_return, e.length) for e in run.train_episodes()] == logged
    check = offline.cross_check(run)
    assert check["checked"] == 3 and not check["mismatches"] and check["missing"] == 0


def test_vector_tasks_run_every_variant_with_an_mlp_through_ros(launch, ros_node, tmp_path):
    """CartPole-v1 (vector observations): the same comper_node picks the mlp Q-network and the
    classic_control profile by itself, stores float32 vector keys in the memory, evaluates greedy
    episodes on a separate environment (~/evaluations, metrics.jsonl, summary.json)."""
    from comper_msgs.msg import EvaluationResult
    runs, evals, batches = {}, {}, {}
    for alg in ("comper", "dqn", "comper_f"):
        tag = f"v{alg}{os.getpid()}"
        name = f"cp_{tag}"
        evals[alg], batches[alg] = [], []
        ros_node.create_subscription(EvaluationResult, f"/{name}/evaluations", evals[alg].append, SUMMARY_QOS)
        ros_node.create_subscription(TransitionBatch, f"/{name}/transitions", batches[alg].append, TRANSITIONS_QOS)
        extra = ["-p", f"algorithm:={alg}", "-p", "total_frames:=1500", "-p", "eval_every:=500",
                 "-p", "eval_episodes:=2", "-p", "learning_starts:=200", "-p", "checkpoint_every:=0",
                 "-p", "diagnostics_every:=50"]
        if alg != "comper":
            extra += ["-p", "n_step:=3"]    # dqn: windows drawn from the replay; comper_f: stored windows
        args = _args(tmp_path, alg, tag, *extra, profile=None)
        args[args.index(f"env_id:={GAME}")] = "env_id:=CartPole-v1"
        runs[alg] = launch("comper_agent", "comper_node", *args, "-r", f"comper_node:__node:={name}", name=alg)
    deadline = time.monotonic() + 200
    while time.monotonic() < deadline and any(p.alive() for p in runs.values()):
        spin_once(ros_node, 0.2)
    for alg, proc in runs.items():
        assert _wait(proc, 30) == 0, proc.log()[-4000:]
    deadline = time.monotonic() + 5
    while time.monotonic() < deadline and any(len(v) < 4 for v in evals.values()):
        spin_once(ros_node, 0.05)
    for alg, proc in runs.items():
        log = proc.log()
        assert "obs [4] float32" in log and "profile classic_control, mlp Q-network, adam" in log, log[-3000:]
        assert "had not acknowledged" not in log    # the last results were handed over before the node ended
        cfg = yaml.safe_load((tmp_path / alg / "config.yaml").read_text())
        assert cfg["q_network"] == "mlp" and cfg["profile"]["name"] == "classic_control"
        assert cfg["learner"]["optimizer"] == "adam" and cfg["learner"]["learning_starts"] == 200  # -p wins
        assert cfg["profile"]["values"]["lr"]["source"]
        assert cfg["learner"]["n_step"] == (1 if alg == "comper" else 3)
        s = json.loads((tmp_path / alg / "summary.json").read_text())
        assert s["sampling"]["n_step"] == cfg["learner"]["n_step"]
        assert s["frames"] == s["steps"] >= 1500 and s["updates"] > 300 and s["complete"]
        steps = [e["step"] for e in s["evaluations"]]
        assert steps[:4] == [0, 500, 1000, 1500] and steps[-1] == s["steps"], steps
        assert all(1 <= len(r["returns"]) <= 2 for r in run_io.MetricsLog.read(tmp_path / alg / "metrics.jsonl", "eval"))
        # ~/evaluations is volatile: a message published before this test's subscription matched
        # the node's publisher may be missed, so check what did arrive against the summary; the last
        # ones may not (the node waits for their acknowledgement before it ends: LearnerHarness.HAND_OVER_S)
        by_step = {e["step"]: e["mean_return"] for e in s["evaluations"]}
        got = [(m.global_step, m.mean_return) for m in evals[alg]]
        assert len(got) >= 3 and all(by_step.get(step) == pytest.approx(ret) for step, ret in got), (got, by_step)
        assert [step for step, _ in got] == steps[len(steps) - len(got):]
        t = batch_to_transitions(batches[alg][0])          # each episode's transitions, raw float32 vectors
        assert t.states.dtype == np.float32 and t.states.shape[1:] == (4,) and np.all(t.rewards == 1.0)
        assert (t.value_labels.shape == (len(t),)) if alg != "dqn" else (t.value_labels.size == 0)
    mem = json.loads((tmp_path / "comper" / "summary.json").read_text())["memory"]
    assert mem["identities"] > 1000 and mem["rtm_size"] > 0
    # qt_diagnostics: only the variant with a QT target writes them, every 50 updates once QT exists
    diag = run_io.MetricsLog.read(tmp_path / "comper" / "metrics.jsonl", "qt_diagnostics")
    assert len(diag) >= 3 and all(d["update"] % 50 == 0 and d["qt_version"] >= 1 for d in diag), diag[:2]
    for d in diag:
        assert d["qt_target_rmse"] >= 0 and d["td_rmse"] >= 0 and d["q_gap_mean"] >= 0 and d["set_size_mean"] >= 1
        assert 0 < d["greedy_top_share"] <= 1 and 0 <= d["label_age_mean"] <= d["step"] and np.isfinite(d["label_bias"])
    assert not any(run_io.MetricsLog.read(tmp_path / alg / "metrics.jsonl", "qt_diagnostics") for alg in ("dqn", "comper_f"))
    # the same figures offline from the final checkpoint and its memory snapshot (benchmarks/comper_final_state.py)
    fs = load_benchmark("comper_final_state").final_state(tmp_path / "comper", batches=5, seed=0)
    final_step = json.loads((tmp_path / "comper" / "summary.json").read_text())["steps"]
    assert fs["step"] == final_step and fs["source"] == "rtm" and fs["memory"]["rtm_size"] > 0
    assert 0 < fs["greedy_top_share"] <= 1 and fs["td_rmse"] >= 0 and np.isfinite(fs["qt_bias"]), fs
    # comper_f with n_step 3: the memory holds 3-step windows (keys [s_t, a_t, return, s_t+3]); CartPole's
    # episodes end by termination (every window kept), so one identity per agent step as for one-step keys
    s = json.loads((tmp_path / "comper_f" / "summary.json").read_text())
    assert s["sampling"]["n_step_windows_dropped"] == 0 and s["memory"]["identities"] > 1000


def test_unknown_or_unsuitable_tasks_are_refused_with_one_line(launch, tmp_path):
    for env_id, words in (("NoSuchTask-v0", "NoSuchTask-v0"), ("Pendulum-v1", "continuous actions")):
        tag = f"bad{abs(hash(env_id)) % 10000}{os.getpid()}"
        args = _args(tmp_path, tag, tag, profile=None)
        args[args.index(f"env_id:={GAME}")] = f"env_id:={env_id}"
        proc = launch("comper_agent", "comper_node", *args, name=tag)
        assert _wait(proc, 60) == 1
        lines = [ln for ln in proc.log().splitlines() if "cannot start" in ln]
        assert len(lines) == 1 and words in lines[0], proc.log()[-2000:]
        assert "Traceback" not in proc.log()

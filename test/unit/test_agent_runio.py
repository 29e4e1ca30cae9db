"""comper_agent.nodes.run_io: run directory, logs, progress line, timers, checkpoints, RNG state."""
import json
import random

import numpy as np
import pytest
import torch

from comper_agent.nodes import run_io


def test_run_dir_config_and_checkpoints_are_atomic_and_weights_only_loadable(tmp_path):
    rd = run_io.RunDir(tmp_path, "r1")
    rd.write_config({"a": (1, 2), "b": np.float32(0.5), "nested": {"x": np.arange(2)}})
    import yaml
    assert yaml.safe_load((rd.path / "config.yaml").read_text()) == {"a": [1, 2], "b": 0.5, "nested": {"x": [0, 1]}}
    for step in (10, 20, 30, 40):
        rd.save_checkpoint({"w": torch.ones(2) * step, "step": step}, step, keep_last=2)
    names = sorted(p.name for p in rd.checkpoints.iterdir())
    assert names == ["latest.pt", "step_000000030.pt", "step_000000040.pt"]   # no temp files left
    payload = torch.load(rd.checkpoints / "latest.pt", weights_only=True)
    assert payload["state"]["step"] == 40
    assert run_io.resolve_checkpoint(rd.path) == rd.checkpoints / "latest.pt"
    assert run_io.resolve_checkpoint(rd.checkpoints / "step_000000030.pt").name == "step_000000030.pt"
    with pytest.raises(FileNotFoundError, match="run directory"):
        run_io.resolve_checkpoint(tmp_path / "nope")


def _companions(rd, step):
    """The replay contents an embedded memory node writes beside the checkpoint of `step`."""
    (rd.replay_path(step, "memory") / "state.npz").parent.mkdir(parents=True, exist_ok=True)
    (rd.replay_path(step, "memory") / "state.npz").write_bytes(b"snapshot")
    return {"kind": "memory", "request": rd.replay_path(step, "memory").name}


def test_pruned_checkpoints_take_their_replay_contents_with_them(tmp_path):
    rd = run_io.RunDir(tmp_path, "r1")
    for step in (10, 20, 30):
        rd.replay_path(step, "local").parent.mkdir(parents=True, exist_ok=True)
        rd.replay_path(step, "local").write_bytes(b"npz")
        _companions(rd, step)
        rd.save_checkpoint({"step": step}, step, keep_last=1)
    assert sorted(p.name for p in rd.checkpoints.iterdir()) == [
        "latest.pt", "step_000000030.memory", "step_000000030.pt", "step_000000030.replay.npz"]


def test_checkpoints_without_their_replay_contents_leave_the_newest_one_with_them(tmp_path):
    """A run whose memory node stopped answering writes final checkpoints with weights and counters only
    (run_io.REPLAY_SKIPPED): pruning keeps the newest checkpoint that has its memory beside it, and a resume
    from the run directory goes back to it; a checkpoint named as a file is taken as it is."""
    rd = run_io.RunDir(tmp_path, "r1")
    for step in (10, 20):
        rd.save_checkpoint({"counters": {"step": step}, "replay": _companions(rd, step)}, step, keep_last=1)
    for step in (21, 22):           # two failed starts in a row: neither may take the memory's checkpoint away
        rd.save_checkpoint({"counters": {"step": step}, run_io.REPLAY_SKIPPED: "a service failed"}, step, keep_last=1)
    assert sorted(p.name for p in rd.checkpoints.iterdir()) == [
        "latest.pt", "step_000000020.memory", "step_000000020.pt", "step_000000022.pt"]
    ck, state, note = run_io.resume_checkpoint(rd.path)
    assert ck.name == "step_000000020.pt" and state["counters"]["step"] == 20 and state["replay"]["kind"] == "memory"
    assert "latest.pt (step 22) holds no memory / replay contents (a service failed)" in note
    assert "continuing from step_000000020.pt" in note
    ck, state, note = run_io.resume_checkpoint(rd.checkpoints / "step_000000022.pt")
    assert ck.name == "step_000000022.pt" and note is None
    # a regular checkpoint after the resume: the usual pruning, down to keep_last
    rd.save_checkpoint({"counters": {"step": 30}, "replay": _companions(rd, 30)}, 30, keep_last=1)
    assert sorted(p.name for p in rd.checkpoints.iterdir()) == ["latest.pt", "step_000000030.memory", "step_000000030.pt"]
    ck, state, note = run_io.resume_checkpoint(rd.path)
    assert ck.name == "latest.pt" and state["counters"]["step"] == 30 and note is None


def test_resume_without_any_checkpoint_holding_replay_contents_takes_latest(tmp_path):
    """Snapshots refused all run long (an external memory node without snapshot_root): every checkpoint is
    marked, none holds the memory, so resume takes latest.pt (the node then warns that the memory refills)
    and pruning goes on as usual."""
    rd = run_io.RunDir(tmp_path, "r1")
    for step in (10, 20, 30):
        rd.save_checkpoint({"counters": {"step": step}, run_io.REPLAY_SKIPPED: "refused"}, step, keep_last=2)
    assert sorted(p.name for p in rd.checkpoints.iterdir()) == ["latest.pt", "step_000000020.pt", "step_000000030.pt"]
    ck, state, note = run_io.resume_checkpoint(rd.path)
    assert ck.name == "latest.pt" and state["counters"]["step"] == 30 and note is None


def test_metrics_log_and_csv(tmp_path):
    m = run_io.MetricsLog(tmp_path / "metrics.jsonl")
    m.write("eval", step=5, mean_return=np.float64(1.5), returns=np.array([1.0, 2.0]))
    m.write("episode", step=6, ret=3.0)
    m.close()
    m.write("eval", step=7)   # after close: ignored, no exception
    with open(tmp_path / "metrics.jsonl", "a") as f:
        f.write('{"kind": "eval", "st')   # a torn line after a crash
    evals = run_io.MetricsLog.read(tmp_path / "metrics.jsonl", "eval")
    assert evals == [{"kind": "eval", "step": 5, "mean_return": 1.5, "returns": [1.0, 2.0]}]
    c = run_io.CsvLog(tmp_path / "p.csv", ["step", "ret"])
    c.write(step=1, ret=2.0, ignored=3)
    c.close()
    c = run_io.CsvLog(tmp_path / "p.csv", ["step", "ret"])   # reopened: no second header
    c.write(step=2, ret=None)
    c.close()
    assert (tmp_path / "p.csv").read_text().splitlines() == ["step,ret", "1,2.0", "2,"]


def test_progress_line_rate_eta_and_rate_limit():
    now = [100.0]
    p = run_io.Progress(1000, period_s=5.0, start_step=0, clock=lambda: now[0])
    assert p.tick(10) is None                   # too early
    now[0] += 10.0
    p.episode(12.5)
    p.evaluation(30.0)
    line = p.tick(200)
    assert "step 200/1000 (20%)" in line and "20 steps/s" in line
    assert "last return 12.5" in line and "last eval 30.0" in line and "ETA 40s" in line
    assert p.tick(201) is None


def test_phase_timers_summary():
    t = run_io.PhaseTimers()
    t.add("sim", 3.0, 100)
    t.add("learner", 1.0, 100)
    with t("io"):
        pass
    s = t.summary(4.0)
    assert s.startswith("sim 75.0% (3.0 s, 100 x 30.00 ms)")
    assert t.as_dict()["learner"] == {"seconds": 1.0, "calls": 100}


def test_rng_state_round_trip_through_a_weights_only_checkpoint(tmp_path):
    from comper_agent.core.checkpoint import load_checkpoint, save_checkpoint
    random.seed(1); np.random.seed(2); torch.manual_seed(3)
    save_checkpoint(tmp_path / "c.pt", {"rng": run_io.rng_state()})
    want = (random.random(), np.random.rand(), torch.rand(1).item())
    random.seed(9); np.random.seed(9); torch.manual_seed(9)
    run_io.set_rng_state(load_checkpoint(tmp_path / "c.pt")["rng"])
    assert (random.random(), np.random.rand(), torch.rand(1).item()) == want


def test_default_run_id_and_duration():
    rid = run_io.default_run_id("comcact", "ALE/Freeway-v5", 3, now=0)
    assert rid.startswith("comcact-ALE_Freeway-v5-s3-")
    assert run_io.format_duration(3725) == "1h02m" and run_io.format_duration(65) == "1m05s"
    assert run_io.format_duration(float("nan")) == "?"

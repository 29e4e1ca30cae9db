"""benchmarks/atari_bench.py and learning_bench.py: which runs a second start of a split sweep does again. A
complete run is done; one stopped before its budget continues from its checkpoint when that holds the memory /
replay contents, and is refused (not silently continued from an empty memory) when it does not. A run whose
last checkpoint a failed service left without them continues from the newest checkpoint that holds them."""
import json
from pathlib import Path

import pytest

from comper_agent.core.checkpoint import save_checkpoint
from scaffolding import load_benchmark


def _bench(name="atari_bench"):
    return load_benchmark(name)


def _run(out: Path, rid: str, complete=None, replay=None, counters=None) -> None:
    d = out / "runs" / rid
    d.mkdir(parents=True)
    if complete is not None:
        (d / "summary.json").write_text(json.dumps({"complete": complete}))
    if replay is not False:
        save_checkpoint(d / "checkpoints" / "latest.pt",
                        {"counters": counters or {"step": 10}, **({"replay": replay} if replay else {})})


def test_split_runs_continue_only_from_a_checkpoint_with_their_memory(tmp_path):
    b = _bench()
    _run(tmp_path, "done", complete=True)
    _run(tmp_path, "stopped", complete=False, replay={"kind": "memory", "request": "step_000000010.memory"})
    _run(tmp_path, "killed", replay={"kind": "local", "file": "step_000000010.replay.npz"})
    _run(tmp_path, "early", replay=False)
    _run(tmp_path, "old", complete=False)
    assert b.run_status(tmp_path, "done") == "done"
    assert b.run_status(tmp_path, "stopped") == "continue" and b.run_status(tmp_path, "killed") == "continue"
    assert b.run_status(tmp_path, "early") == "new" and b.run_status(tmp_path, "absent") == "new"
    with pytest.raises(ValueError, match="holds no memory / replay contents"):
        b.run_status(tmp_path, "old")


def test_learning_bench_skips_runs_at_their_budget_and_continues_stopped_ones(tmp_path):
    b = _bench("learning_bench")
    args = b.parse_args(["--tasks", "Hopper-v4", "CartPole-v1", "--algorithms", "ddpg", "dqn", "sb3_ddpg",
                         "--total-steps", "50000", "--out", str(tmp_path), "--tag", "t"])
    base = tmp_path / "t"
    mem = {"kind": "memory", "request": "step_000030000.memory"}
    _run(base, "ddpg-Hopper-v4-s0", replay=mem, counters={"step": 50000})
    _run(base, "ddpg-Hopper-v4-s1", replay=mem, counters={"step": 30000})
    _run(base, "ddpg-Hopper-v4-s2", counters={"step": 30000})
    _run(base, "dqn-CartPole-v1-s0", replay={"kind": "local", "file": "x.npz"}, counters={"step": 60000, "frames": 40000})
    assert b.run_status(args, base, "ddpg", "Hopper-v4", 0) == "done"
    assert b.run_status(args, base, "ddpg", "Hopper-v4", 1) == "continue"
    assert b.run_status(args, base, "dqn", "CartPole-v1", 0) == "continue"      # the budget counts its frames
    assert b.run_status(args, base, "ddpg", "CartPole-v1", 0) == "new"
    with pytest.raises(ValueError, match="holds no memory / replay contents"):
        b.run_status(args, base, "ddpg", "Hopper-v4", 2)
    sb3 = base / "runs" / "sb3_ddpg-Hopper-v4-s0"
    sb3.mkdir(parents=True)
    (sb3 / "metrics.jsonl").write_text(json.dumps({"kind": "eval", "step": 5000}) + "\n")
    assert b.run_status(args, base, "sb3_ddpg", "Hopper-v4", 0) == "new"         # stopped early: starts again
    with open(sb3 / "metrics.jsonl", "a") as f:
        f.write(json.dumps({"kind": "timers", "steps": 50000, "elapsed_s": 900.0}) + "\n")
    assert b.run_status(args, base, "sb3_ddpg", "Hopper-v4", 0) == "done"


def test_a_run_stopped_by_a_failed_service_continues_from_its_last_checkpoint_with_memory(tmp_path):
    """The memory node did not answer in time, so the final checkpoint holds weights and counters only
    (run_io.REPLAY_SKIPPED): the bench continues the run (from the older checkpoint that holds the memory)
    instead of refusing it."""
    from comper_agent.nodes import run_io
    b = _bench()
    d = tmp_path / "runs" / "failed"
    rd = run_io.RunDir(tmp_path / "runs", "failed")
    (d / "checkpoints" / "step_000007500.memory").mkdir(parents=True)
    rd.save_checkpoint({"counters": {"step": 7500, "frames": 37461},
                        "replay": {"kind": "memory", "request": "step_000007500.memory"}}, 7500)
    rd.save_checkpoint({"counters": {"step": 7501, "frames": 37466},
                        run_io.REPLAY_SKIPPED: "a service failed"}, 7501)
    assert b.run_status(tmp_path, "failed") == "continue"

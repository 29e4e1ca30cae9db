"""A benchmark stopped with SIGTERM (or Ctrl-C) stops the runs it started: they run in sessions of their
own (a terminal's Ctrl-C misses them), so without this they went on without the benchmark, still holding
a ROS domain the next benchmark could take. Here learning_bench starts one real comper_node run
(CartPole-v1, dqn), gets SIGTERM once the run is under way, and the run ends as on its own Ctrl-C. Started
again, the bench continues that run from its checkpoint (replay contents included) to its budget, and a third
start finds nothing left to run."""
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

from conftest import ROOT


def _node_pids(marker: str) -> list[int]:
    out = subprocess.run(["pgrep", "-f", marker], capture_output=True, text=True).stdout.split()
    return [int(p) for p in out if int(p) != os.getpid()]


def test_sigterm_to_the_bench_stops_its_runs_with_their_final_checkpoint(tmp_path):
    out = tmp_path / "bench"
    cmd = [sys.executable, str(ROOT / "benchmarks" / "learning_bench.py"), "--tasks", "CartPole-v1",
           "--algorithms", "dqn", "--seeds", "1", "--total-steps", "200000", "--eval-every", "0",
           "--parallel", "1", "--out", str(out), "--tag", "t"]
    bench = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                             start_new_session=True)
    run = out / "t" / "runs" / "dqn-CartPole-v1-s0"
    try:
        deadline = time.monotonic() + 120
        while not (run / "metrics.jsonl").exists() or "progress" not in (run / "metrics.jsonl").read_text():
            assert bench.poll() is None and time.monotonic() < deadline, "the run never got going"
            time.sleep(0.5)
        assert _node_pids(str(run.parent)), "no node process found for the run"
        bench.send_signal(signal.SIGTERM)
        log, _ = bench.communicate(timeout=150)
    finally:
        if bench.poll() is None:
            os.killpg(bench.pid, signal.SIGKILL)
        leftovers = _node_pids(str(run.parent))
        for pid in leftovers:                   # a failing run of this test leaves nothing behind either
            try:
                os.killpg(os.getpgid(pid), signal.SIGKILL)
            except ProcessLookupError:
                pass
    assert "interrupted: stopping 1 run(s) in progress" in log, log
    assert not leftovers, "the run's node outlived the benchmark"
    summary = json.loads((run / "summary.json").read_text())
    assert summary["complete"] is False and 0 < summary["steps"] < 200000
    assert (run / "checkpoints" / "latest.pt").exists()
    claims = Path(os.environ.get("TMPDIR", "/tmp")) / "comper-ros-domains"    # learning_bench.DOMAIN_CLAIMS
    held = [f.name for f in claims.glob("*") if f.read_text().strip() == str(bench.pid)]
    assert not held, f"ROS domain(s) {held} still claimed by the stopped benchmark"

    # the second start (budget: 300 steps past where it stopped) continues the run; the third has nothing to do
    stopped_at, step = summary["frames"], summary["steps"]          # its budget counts frames
    again = cmd[:cmd.index("--total-steps") + 1] + [str(stopped_at + 300)] + cmd[cmd.index("--total-steps") + 2:]
    second = subprocess.run(again, capture_output=True, text=True, timeout=300)
    assert second.returncode == 0 and "continue dqn-CartPole-v1-s0" in second.stdout, second.stdout + second.stderr
    node_log = (out / "t" / "logs" / "dqn-CartPole-v1-s0.log").read_text()
    assert f"resuming at step {step}" in node_log and "replay buffer restored" in node_log, node_log[-3000:]
    summary = json.loads((run / "summary.json").read_text())
    assert summary["complete"] is True and summary["frames"] >= stopped_at + 300      # its last episode ends
    third = subprocess.run(again, capture_output=True, text=True, timeout=120)
    assert "already at their budget, not run again: dqn-CartPole-v1-s0" in third.stdout, third.stdout

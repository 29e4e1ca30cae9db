"""`ros2 run comper_agent bringup`: the suite as supervised separate processes (sim, memory, QT trainer,
comcact_node with bringup:=external), real ROS, no mocks. A short job runs to its end and the servers are
stopped cleanly; Ctrl-C (SIGINT to the supervisor) is forwarded and the learner saves; a node killed
from outside is reported with its exit status and the others are stopped, the bring-up exits non-zero; the
nodes stop when the supervisor itself is killed; checkpoints hold the memory and a resumed bring-up continues
with it, as the embedded bring-up's do."""
import os
import re
import signal
import subprocess
import time

import pytest
import torch

from conftest import ros2_command

TAG = os.getpid()
NAMES = {"sim_node": f"sim_b{TAG}", "memory_node": f"mem_b{TAG}", "qt_trainer_node": f"qt_b{TAG}"}
LEARNER = f"learner_b{TAG}"


class Bringup:
    def __init__(self, tmp_path, run_id, *params, stop_timeout=20, log_name=None):
        self.log_path = tmp_path / f"bringup_{log_name or run_id}.log"
        self._log = open(self.log_path, "wb")
        args = ["-p", "env_id:=InvertedPendulum-v4", "-p", f"runs_root:={tmp_path}", "-p", f"run_id:={run_id}",
                "-p", "tensorboard:=false", "-p", "transport_probe_calls:=0", "-p", "progress_period_s:=1.0",
                "-p", "eval_episodes:=1", "-r", f"__node:={LEARNER}",
                *[x for k, v in NAMES.items() for x in ("-p", f"{k}:={v}")], *params]
        self.proc = subprocess.Popen([ros2_command(), "run", "comper_agent", "bringup", "--stop-timeout",
                                      str(stop_timeout), "--ros-args", *args],
                                     stdout=self._log, stderr=subprocess.STDOUT, start_new_session=True)

    def log(self) -> str:
        self._log.flush()
        return self.log_path.read_text(errors="replace")

    def wait_for(self, pattern, timeout=300):
        deadline = time.monotonic() + timeout
        while not re.search(pattern, self.log(), re.M):
            if self.proc.poll() is not None or time.monotonic() > deadline:
                raise AssertionError(f"no {pattern!r} in the bring-up's output:\n{self.log()[-5000:]}")
            time.sleep(0.5)
        return re.search(pattern, self.log(), re.M)

    def wait(self, timeout=300) -> int:
        try:
            return self.proc.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            raise AssertionError(f"the bring-up did not end within {timeout} s:\n{self.log()[-5000:]}")

    def close(self):
        if self.proc.poll() is None:
            os.killpg(self.proc.pid, signal.SIGKILL)
            self.proc.wait()
        self._log.close()

    def exit_codes(self) -> dict:
        line = self.wait_for(r"^\[bringup\] exit codes: (.*); bring-up exits with (-?\d+)$").group(1)
        return {name: int(code) for name, code in (part.rsplit(" ", 1) for part in line.split(", "))}


@pytest.fixture
def bringup(tmp_path):
    started = []

    def _start(*args, **kw):
        b = Bringup(tmp_path, *args, **kw)
        started.append(b)
        return b

    yield _start
    for b in started:
        b.close()


def _checkpoint_step(tmp_path, run_id):
    return torch.load(tmp_path / run_id / "checkpoints" / "latest.pt", weights_only=True)["state"]["counters"]["step"]


def test_short_job_prefixed_logs_and_clean_stop(bringup, tmp_path):
    b = bringup("short", "-p", "total_steps:=200", "-p", "eval_every:=100")
    assert b.wait() == 0, b.log()[-5000:]
    log = b.log()
    for name in (*NAMES.values(), LEARNER):
        assert re.search(rf"^\[bringup\] started {name} \(pid \d+\)", log, re.M), name
    assert re.search(rf"^\[{NAMES['sim_node']}\] .*serving InvertedPendulum-v4", log, re.M)
    assert re.search(rf"^\[{NAMES['qt_trainer_node']}\] .*QT trainer ready", log, re.M)
    assert re.search(rf"^\[{LEARNER}\] .*external bring-up", log, re.M)
    assert re.search(rf"^\[{LEARNER}\] .*final checkpoint", log, re.M)
    assert f"[bringup] {LEARNER} finished; stopping the servers" in log
    assert b.exit_codes() == {**{n: 0 for n in NAMES.values()}, LEARNER: 0}
    assert _checkpoint_step(tmp_path, "short") == 200
    # every line came from a named process or the supervisor
    assert all(re.match(r"^\[[\w.]+\] ", line) for line in log.splitlines() if line), log[-3000:]


def test_sigint_is_forwarded_and_the_learner_saves(bringup, tmp_path):
    b = bringup("sigint", "-p", "total_steps:=100000", "-p", "eval_every:=0")
    b.wait_for(rf"^\[{LEARNER}\] .*step \d+/100000")
    os.kill(b.proc.pid, signal.SIGINT)
    assert b.wait() == 0, b.log()[-5000:]
    log = b.log()
    assert "[bringup] signal received: stopping" in log
    assert re.search(rf"^\[{LEARNER}\] .*stop requested", log, re.M)
    assert b.exit_codes() == {**{n: 0 for n in NAMES.values()}, LEARNER: 0}
    assert 0 < _checkpoint_step(tmp_path, "sigint") < 100000


def test_a_node_that_dies_is_reported_and_the_rest_are_stopped(bringup, tmp_path):
    b = bringup("kill", "-p", "total_steps:=100000", "-p", "eval_every:=0", "-p", "service_timeout_s:=10",
                "-p", "call_timeout_s:=5",  # the QT trainer waits this long on the dead memory, then can stop
                stop_timeout=20)
    mem_pid = int(b.wait_for(rf"^\[bringup\] started {NAMES['memory_node']} \(pid (\d+)\)").group(1))
    b.wait_for(rf"^\[{LEARNER}\] .*step \d+/100000")
    os.killpg(mem_pid, signal.SIGKILL)
    rc = b.wait()
    log = b.log()
    assert rc == 128 + signal.SIGKILL, log[-5000:]
    assert f"[bringup] {NAMES['memory_node']} was killed by SIGKILL; stopping the others" in log
    codes = b.exit_codes()
    assert codes[NAMES["memory_node"]] == -signal.SIGKILL
    assert codes[NAMES["sim_node"]] == 0 and codes[NAMES["qt_trainer_node"]] == 0      # stopped cleanly by SIGINT
    assert isinstance(codes[LEARNER], int)
    for name in NAMES.values():
        pid = int(re.search(rf"^\[bringup\] started {name} \(pid (\d+)\)", log, re.M).group(1))
        with pytest.raises(ProcessLookupError):
            os.kill(pid, 0)


def test_the_nodes_stop_when_the_supervisor_itself_is_killed(bringup, tmp_path):
    b = bringup("orphan", "-p", "algorithm:=ddpg", "-p", "total_steps:=100000", "-p", "eval_every:=0")
    b.wait_for(rf"^\[{LEARNER}\] .*step \d+/100000")
    log = b.log()
    pids = {int(re.search(rf"^\[bringup\] started {name} \(pid (\d+)\)", log, re.M).group(1)): name
            for name in (NAMES["sim_node"], LEARNER)}
    os.kill(b.proc.pid, signal.SIGKILL)           # the supervisor only: its children are in their own sessions
    b.proc.wait()
    deadline = time.monotonic() + 120
    alive = list(pids)
    while alive and time.monotonic() < deadline:
        alive = [p for p in alive if _running(p)]
        time.sleep(0.5)
    # the kernel signals every child at once here (no learner-first order), so a final checkpoint is not promised
    assert not alive, (f"still running after the supervisor was killed: {[(p, pids[p]) for p in alive]}\n"
                       + b.log()[-5000:])


def _snapshot_stats(path) -> dict:
    """What a memory snapshot holds: loaded into a memory core of the node's default configuration."""
    from comper_memory.core import CompactMemory, MemoryConfig
    memory = CompactMemory(MemoryConfig())
    memory.load_snapshot(str(path))
    return memory.stats()


@pytest.mark.slow      # two bring-ups, each starting four processes (40-90 s on 2 busy cores)
def test_a_resumed_bring_up_continues_with_the_memory_it_had(bringup, tmp_path):
    """Each checkpoint of the separate processes holds the memory, beside step_<N>.pt in the run directory and
    pruned with it; Ctrl-C, then a bring-up with resume: its memory node holds what the first one had."""
    b = bringup("resume", "-p", "total_steps:=100000", "-p", "eval_every:=0", "-p", "checkpoint_every:=150",
                "-p", "keep_checkpoints:=1")
    b.wait_for(rf"^\[{LEARNER}\] .*checkpoint: \S+step_0000003\d\d\.pt \(with the memory's snapshot")   # the 2nd
    os.kill(b.proc.pid, signal.SIGINT)
    assert b.wait() == 0, b.log()[-5000:]
    assert "checkpoints hold no memory contents" not in b.log()
    checkpoints = tmp_path / "resume" / "checkpoints"
    state = torch.load(checkpoints / "latest.pt", weights_only=True)["state"]
    step, saved = state["counters"]["step"], state["replay"]
    name = f"step_{step:09d}.memory"
    assert saved["kind"] == "memory" and saved["request"] == name
    assert os.path.samefile(saved["path"], checkpoints / name)
    # keep_checkpoints 1: the older step files went, each with its memory snapshot
    assert sorted(p.name for p in checkpoints.glob("step_*")) == [name, f"step_{step:09d}.pt"]
    had = _snapshot_stats(checkpoints / name)
    assert had["identities"] > 0 and had["rtm_size"] >= 0

    b2 = bringup("resume", "-p", f"resume:={tmp_path / 'resume'}", "-p", f"total_steps:={step + 100}",
                 "-p", "eval_every:=0", "-p", "checkpoint_every:=150", "-p", "keep_checkpoints:=1",
                 log_name="resumed")
    assert b2.wait() == 0, b2.log()[-5000:]
    restored = b2.wait_for(rf"^\[{LEARNER}\] .*memory restored from (\S+): (\d+) identities, TM sets (\d+), "
                           r"RTM (\d+)")
    assert restored.group(1) == os.path.realpath(checkpoints / name)      # (pruned by now: the run went on)
    assert [int(x) for x in restored.groups()[1:]] == [had["identities"], had["tm_sets"], had["rtm_size"]]
    assert "checkpoints hold no memory contents" not in b2.log()
    assert _checkpoint_step(tmp_path, "resume") == step + 100


def _running(pid) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0] != "Z"
    except FileNotFoundError:
        return False

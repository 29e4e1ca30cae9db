"""The memory node's secure defaults, through real node processes (`ros2 run`): snapshot names and the
quota on named snapshots, restores refused to peers unless enabled, the start-up restore, requested
ROS 2 security that cannot be in force ending in one `cannot start` line (memory node and a learner),
and DDS discovery kept on this host by the entry points unless a range is chosen (docs/security.md)."""
from __future__ import annotations

import contextlib
import os
import re
import shutil
import subprocess
import threading
import time
from pathlib import Path

import pytest

from memory_worker import make_batch
from test_memory_node import client_of, refused, start  # noqa: F401 - fixture

ROOT = Path(__file__).resolve().parents[2]
STATE = ("identities", "tm_sets", "rtm_size", "transitions_stored", "reductions", "sets_reduced")


def wait_exit(proc, timeout=60.0):
    try:
        return proc.proc.wait(timeout=timeout)
    except subprocess.TimeoutExpired:
        raise AssertionError(f"{proc.name} did not exit:\n{proc.log()}") from None


def state(memory):
    s = memory.stats()
    return {k: s[k] for k in STATE}


def files_under(root: Path) -> list[str]:
    return sorted(str(p.relative_to(root)) for p in root.rglob("*"))


def test_snapshot_names_and_the_quota_are_bounded(launch, client_of, tmp_path):
    storage = tmp_path / "storage"
    root = storage / "snapshots"
    proc, name = start(launch, "quota", "-p", f"storage_dir:={storage}", "-p", "snapshot_every:=0",
                       "-p", "snapshot_max_count:=3")
    memory = client_of(name)
    memory.store(make_batch(7, 0, 32))
    before = memory.stats()
    # names: a long one (it was an OSError), characters outside the rule, too many parts, hidden, reserved
    refused(proc, lambda: memory.snapshot("x" * 5000), "5000 characters", "at most 200 characters")
    msg = refused(proc, lambda: memory.restore("x" * 5000), "restore is off", "snapshot_restore:=NAME")
    assert len(msg) < 1000, "the refusal echoes the name"
    refused(proc, lambda: memory.snapshot("my snap"), "'my snap'", "holds ' '", "letters, digits")
    refused(proc, lambda: memory.snapshot("a/b/c/d/e"), "5 parts")
    refused(proc, lambda: memory.snapshot(".hidden"), "starts with '.'")
    refused(proc, lambda: memory.snapshot("s.tmp-99"), "temporary copies")
    refused(proc, lambda: memory.snapshot("../escape"), "outside snapshot_root")
    assert not root.exists() or files_under(root) == []
    # the quota on their number: a new name beyond it is refused and nothing of it is written
    for n in ("s1", "run-1/step_000000100.memory", "s3"):
        memory.snapshot(n)
    listing = files_under(root)
    msg = refused(proc, lambda: memory.snapshot("s4"), "'s4'", "holds 3 named snapshots", "snapshot_max_count is 3",
                  "delete named snapshots", "-p snapshot_max_count:=N")
    assert str(root) in msg
    assert files_under(root) == listing, "a refused save left something behind"
    path, _ = memory.snapshot("s1")                    # replacing one is not a new one
    assert path == str(root / "s1") and files_under(root) == listing
    shutil.rmtree(root / "s3")                          # freed: the next name fits
    memory.snapshot("s4")
    assert memory.stats()["identities"] == before["identities"] and proc.alive()
    assert proc.stop() == 0
    # the quota on their bytes (checked before writing); the node's own storage snapshot is not named
    proc2, name2 = start(launch, "quota2", "-p", f"storage_dir:={storage}", "-p", "snapshot_every:=0",
                         "-p", "snapshot_max_count:=0", "-p", "snapshot_max_bytes:=1")
    memory = client_of(name2)
    listing = files_under(root)
    refused(proc2, lambda: memory.snapshot("s5"), "'s5'", "beyond snapshot_max_bytes", "-p snapshot_max_bytes:=N")
    refused(proc2, lambda: memory.snapshot("s1"), "beyond snapshot_max_bytes")
    assert files_under(root) == listing
    path, _ = memory.snapshot("")
    assert path == str(storage / "snapshot")
    assert proc2.stop() == 0


def test_peers_may_not_restore_by_default_the_start_up_restore_and_save_restore_may(launch, client_of, tmp_path):
    storage = tmp_path / "storage"
    proc, name = start(launch, "norestore", "-p", f"storage_dir:={storage}", "-p", "snapshot_every:=0")
    memory = client_of(name)
    for j in range(3):
        memory.store(make_batch(8, j, 16))
    memory.snapshot("run/step_1.memory")
    saved = state(memory)
    memory.store(make_batch(8, 9, 16))
    later = state(memory)
    assert later != saved
    refused(proc, lambda: memory.restore("run/step_1.memory"), "restore is off", "snapshot_service save",
            "-p snapshot_restore:=run/step_1.memory", "-p snapshot_service:=save_restore")
    refused(proc, lambda: memory.restore(""), "restore is off")
    assert state(memory) == later
    assert proc.stop() == 0

    # the start-up restore: the node starts with the snapshot's state
    proc, name = start(launch, "startrestore", "-p", f"storage_dir:={storage}", "-p", "snapshot_every:=0",
                       "-p", "snapshot_restore:=run/step_1.memory")
    memory = client_of(name)
    assert state(memory) == saved
    assert "restored at start-up from" in proc.log()
    # a peer asking for that same restore while nothing changed is answered, and nothing happens
    path, _ = memory.restore("run/step_1.memory")
    assert path == str(storage / "snapshots" / "run" / "step_1.memory") and state(memory) == saved
    memory.store(make_batch(8, 10, 16))
    changed = state(memory)
    refused(proc, lambda: memory.restore("run/step_1.memory"), "restore is off")
    assert state(memory) == changed
    assert proc.stop() == 0
    # with storage_dir the restored state was checkpointed: a start without snapshot_restore continues it
    proc, name = start(launch, "afterrestore", "-p", f"storage_dir:={storage}", "-p", "snapshot_every:=0",
                       "-p", "snapshot_service:=save_restore")
    memory = client_of(name)
    assert state(memory) == changed
    # restores allowed when asked for
    path, _ = memory.restore("run/step_1.memory")
    assert state(memory) == saved
    assert proc.stop() == 0
    # a start-up restore that cannot be done stops start-up with one line
    proc, _ = start(launch, "badrestore", "-p", f"storage_dir:={storage}", "-p", "snapshot_restore:=missing")
    assert wait_exit(proc) == 1
    log = proc.log()
    assert "cannot start" in log and "snapshot_restore 'missing'" in log and "not a snapshot directory" in log
    assert "Traceback" not in log, log


def run_entry_point(package, executable, env_changes, cwd, *args, timeout=120):
    env = {k: v for k, v in os.environ.items() if not k.startswith("ROS_SECURITY_")}
    env.update(env_changes)
    done = subprocess.run([shutil.which("ros2"), "run", package, executable, *args], env=env, cwd=cwd,
                          capture_output=True, text=True, timeout=timeout)
    return done.returncode, done.stdout + done.stderr


def test_requested_security_that_cannot_be_in_force_is_one_cannot_start_line(tmp_path):
    pypi = subprocess.run([str(ROOT / "scripts" / "ros_install.sh"), "detect"], capture_output=True,
                          text=True).stdout.split()[:1] == ["pypi"]
    keystore = tmp_path / "keystore"
    (keystore / "enclaves" / "comper").mkdir(parents=True)
    cases = [({"ROS_SECURITY_ENABLE": "true"}, "ROS_SECURITY_KEYSTORE is not set"),     # Enforce by default
             ({"ROS_SECURITY_ENABLE": "true", "ROS_SECURITY_KEYSTORE": str(tmp_path / "none")},
              "'/enclaves' does not exist"),
             ({"ROS_SECURITY_ENABLE": "true", "ROS_SECURITY_KEYSTORE": str(keystore)},
              "has no DDS-Security" if pypi else "")]
    for env, why in cases:
        rc, out = run_entry_point("comper_memory", "memory_node", env, tmp_path, "--ros-args", "-p",
                                  "stats_period_s:=0")
        lines = [ln for ln in out.splitlines() if "cannot start" in ln]
        assert rc == 1 and len(lines) == 1, (env, out)
        assert "cannot start: ROS 2 security is requested (ROS_SECURITY_ENABLE=true" in lines[0], out
        assert why.replace("'/enclaves'", f"'{tmp_path / 'none'}/enclaves'") in lines[0], out
        assert "Traceback" not in out and "RCLError" not in out, out
    # a learner's entry point says it the same way, before it makes a run directory
    rc, out = run_entry_point("comper_agent", "comcact_node", {"ROS_SECURITY_ENABLE": "true"}, tmp_path,
                              "--ros-args", "-p", "env_id:=InvertedPendulum-v4", "-p", f"runs_root:={tmp_path}/runs")
    assert rc == 1 and "cannot start: ROS 2 security is requested" in out and "Traceback" not in out, out
    assert not (tmp_path / "runs").exists()
    # Permissive, chosen explicitly, runs without security (rcl's meaning) and says so
    proc = subprocess.Popen([shutil.which("ros2"), "run", "comper_memory", "memory_node", "--ros-args", "-r",
                             f"__node:=permissive_{os.getpid()}"], cwd=tmp_path, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True, start_new_session=True,
                            env={**os.environ, "ROS_SECURITY_ENABLE": "true", "ROS_SECURITY_STRATEGY": "Permissive"})
    watchdog = threading.Timer(60.0, lambda: os.killpg(proc.pid, 9))     # a node that never serves
    watchdog.start()
    try:
        out = ""
        for line in proc.stdout:
            out += line
            if "serving" in line:
                break
    finally:
        watchdog.cancel()
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, 2)
        out += proc.communicate(timeout=30)[0]
    assert "security is requested but NOT in force" in out and "serving" in out and proc.returncode == 0, out


def _udp_ports_of_group(pgid: int) -> set[int]:
    pids = set()
    for d in Path("/proc").iterdir():
        if d.name.isdigit():
            try:
                if int((d / "stat").read_text().rsplit(")", 1)[1].split()[2]) == pgid:
                    pids.add(int(d.name))
            except (OSError, IndexError, ValueError):
                pass
    out = subprocess.run(["ss", "-ulpnH"], capture_output=True, text=True).stdout
    ports = set()
    for line in out.splitlines():
        if any(re.search(rf"pid={p}\b", line) for p in pids):
            ports.add(int(line.split()[3].rsplit(":", 1)[1]))
    return ports


@pytest.mark.skipif(shutil.which("ss") is None, reason="needs ss (iproute2) to see the node's sockets")
def test_node_entry_points_keep_discovery_on_this_host_unless_a_range_is_chosen(tmp_path):
    """Fast DDS listens on the domain's discovery multicast port (7400 + 250 * domain) only when discovery
    reaches beyond the host; an entry point started without a range chosen does not."""
    multicast = 7400 + 250 * int(os.environ["ROS_DOMAIN_ID"])
    seen = {}
    for chosen in ("", "SUBNET"):
        log = tmp_path / f"range{chosen}.log"
        with open(log, "w") as f:
            proc = subprocess.Popen([shutil.which("ros2"), "run", "comper_memory", "memory_node", "--ros-args", "-r",
                                     f"__node:=range{chosen}_{os.getpid()}", "-p", "stats_period_s:=0"],
                                    cwd=tmp_path, stdout=f, stderr=subprocess.STDOUT, start_new_session=True,
                                    env={**os.environ, "ROS_AUTOMATIC_DISCOVERY_RANGE": chosen})
        try:
            deadline = time.monotonic() + 60
            while "serving" not in log.read_text() and proc.poll() is None and time.monotonic() < deadline:
                time.sleep(0.1)
            assert "serving" in log.read_text(), log.read_text()
            seen[chosen] = _udp_ports_of_group(proc.pid)
        finally:
            os.killpg(proc.pid, 2)
            assert proc.wait(timeout=30) == 0, log.read_text()
    assert seen[""] and multicast not in seen[""], seen          # unset: LOCALHOST
    assert multicast in seen["SUBNET"], seen

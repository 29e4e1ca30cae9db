"""Named snapshots' rules (comper_memory.snapshot_rules): names, the quota and its size bound, and the
entry points' environment defaults and security diagnosis (comper_msgs_py.ros_main), without ROS nodes."""
from __future__ import annotations

import os

import numpy as np
import pytest

from comper_memory.core import CompactMemory, MemoryConfig, SnapshotError
from comper_memory.core.storage import write_snapshot
from comper_memory.snapshot_rules import NAME_MAX, SnapshotQuota, check_name, size_bound, usage
from comper_msgs_py.ros_main import apply_env_defaults, security_problem


def state(n, seed=0):
    """(arrays, meta) shaped like a memory's snapshot: frames, keys, labels, ids, counters."""
    rng = np.random.default_rng(seed)
    arrays = {"obs": rng.integers(0, 256, (n, 4, 84, 84), dtype=np.uint8), "keys": rng.random((n, 26), np.float32),
              "labels": rng.random((n, 32), np.float32), "ids": np.arange(n, dtype=np.int64),
              "done": rng.random(n) < 0.1, "empty": np.zeros((0, 3), np.float64)}
    return arrays, {"schema": {"obs_shape": [4, 84, 84], "key_size": 26}, "counters": {"next_id": n}}


@pytest.mark.parametrize("name", ["a", "snap1", "step_000000100.memory", "_x",
                                  "comcact-ALE_Freeway-v5-s0-20261207-101010/step_000005000.memory",
                                  "a/b/c/d", "x" * NAME_MAX])
def test_the_learners_names_and_plain_names_pass(name):
    check_name(name)


@pytest.mark.parametrize("name, words", [
    ("x" * (NAME_MAX + 1), [f"{NAME_MAX + 1} characters", f"at most {NAME_MAX}"]),
    ("a/b/c/d/e", ["5 parts"]), ("a b", ["holds ' '"]), ("semi;colon", ["holds ';'"]), ("ümlaut", ["holds 'ü'"]),
    (".hidden", ["starts with '.'"]), ("-rf", ["starts with '-'"]), ("..", ["starts with '.'"]),
    ("run/.x", ["part '.x'"]), ("x.tmp-12", ["temporary copies"]), ("a/b.old-3", ["temporary copies"]),
])
def test_names_outside_the_rule_are_refused_with_the_rule(name, words):
    with pytest.raises(SnapshotError) as err:
        check_name(name)
    for w in words:
        assert w in str(err.value), str(err.value)


def test_usage_counts_snapshot_directories_to_the_name_depth_without_following_links(tmp_path):
    arrays, meta = state(20)
    root = tmp_path / "root"
    for name in ("a", "run/b", "run/deep/er/c", "x/y/z/w/too_deep"):
        write_snapshot(str(root / name), arrays, meta)
    (root / "other").mkdir()
    (root / "other" / "file.txt").write_text("not a snapshot")
    outside = tmp_path / "outside"
    write_snapshot(str(outside / "s"), arrays, meta)
    (root / "link").symlink_to(outside, target_is_directory=True)
    one = sum(f.stat().st_size for f in (root / "a").iterdir())
    assert usage(str(root)) == (3, 3 * one)          # a, run/b, run/deep/er/c; not 5 levels down, not via the link
    assert usage(str(root), exclude=str(root / "run" / "b")) == (2, 2 * one)
    assert usage(str(tmp_path / "missing")) == (0, 0)


@pytest.mark.parametrize("n", [0, 1, 300])
def test_the_size_bound_is_at_least_what_the_snapshot_takes(tmp_path, n):
    arrays, meta = state(n)
    write_snapshot(str(tmp_path / "s"), arrays, meta)
    actual = sum(f.stat().st_size for f in (tmp_path / "s").iterdir())
    assert actual <= size_bound(arrays, meta) <= actual + 32 * 1024, (actual, size_bound(arrays, meta))


def test_the_memory_shows_its_snapshot_to_admit_before_writing(tmp_path):
    mem, seen = CompactMemory(MemoryConfig()), []
    mem.save_snapshot(str(tmp_path / "s"), admit=lambda arrays, meta: seen.append(size_bound(arrays, meta)))
    actual = sum(f.stat().st_size for f in (tmp_path / "s").iterdir())
    assert actual <= seen[0] <= actual + 32 * 1024


def test_a_save_its_admit_refuses_writes_nothing(tmp_path):
    mem = CompactMemory(MemoryConfig())

    def refuse(arrays, meta):
        raise SnapshotError("over the quota")

    with pytest.raises(SnapshotError, match="over the quota"):
        mem.save_snapshot(str(tmp_path / "root" / "s"), admit=refuse)
    assert not (tmp_path / "root").exists()


def test_the_quota_refuses_with_how_to_free_or_raise_it(tmp_path):
    root, target = str(tmp_path), str(tmp_path / "new")
    SnapshotQuota(max_count=3).check(root, target, 2, 0, 10)          # the third one fits
    with pytest.raises(SnapshotError) as err:
        SnapshotQuota(max_count=3).check(root, target, 3, 0, 10)
    msg = str(err.value)
    assert "'new'" in msg and "snapshot_max_count is 3" in msg and "delete named snapshots" in msg
    assert "-p snapshot_max_count:=N" in msg
    SnapshotQuota(max_bytes=100).check(root, target, 9, 60, 40)
    with pytest.raises(SnapshotError, match=r"beyond snapshot_max_bytes .*-p snapshot_max_bytes:=N"):
        SnapshotQuota(max_bytes=100).check(root, target, 9, 61, 40)
    free = os.statvfs(root).f_bavail * os.statvfs(root).f_frsize
    SnapshotQuota(min_free_bytes=1).check(root, target, 0, 0, 10)
    with pytest.raises(SnapshotError, match=r"snapshot_min_free_bytes .*-p snapshot_min_free_bytes:=N"):
        SnapshotQuota(min_free_bytes=free).check(root, target, 0, 0, 10)
    SnapshotQuota().check(root, target, 10**6, 2**62, 2**40)          # all bounds off


def test_entry_points_keep_discovery_local_unless_a_range_was_chosen():
    env = {}
    assert apply_env_defaults(env) == {"ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST"} and \
        env["ROS_AUTOMATIC_DISCOVERY_RANGE"] == "LOCALHOST"
    for chosen in ({"ROS_AUTOMATIC_DISCOVERY_RANGE": "SUBNET"}, {"ROS_LOCALHOST_ONLY": "0"}):
        env = dict(chosen)
        assert apply_env_defaults(env) == {} and env == chosen
    env = {"ROS_AUTOMATIC_DISCOVERY_RANGE": ""}                       # empty = not chosen, as rcl reads it
    apply_env_defaults(env)
    assert env["ROS_AUTOMATIC_DISCOVERY_RANGE"] == "LOCALHOST"


def test_requested_security_means_enforce_and_its_failures_read_as_one_line():
    env = {"ROS_SECURITY_ENABLE": "true", "ROS_AUTOMATIC_DISCOVERY_RANGE": "SUBNET"}
    assert apply_env_defaults(env) == {"ROS_SECURITY_STRATEGY": "Enforce"}
    env = {"ROS_SECURITY_ENABLE": "true", "ROS_SECURITY_STRATEGY": "Permissive", "ROS_LOCALHOST_ONLY": "1"}
    assert apply_env_defaults(env) == {}                              # an explicit choice stays
    err = RuntimeError("error creating node: This Fast DDS version doesn't have the security libraries\nPlease "
                       "compile Fast DDS using the -DSECURITY=ON CMake option, at /project/src/participant.cpp:364")
    line = security_problem(err, {"ROS_SECURITY_ENABLE": "true", "ROS_SECURITY_STRATEGY": "Enforce",
                                  "ROS_SECURITY_KEYSTORE": "/k"})
    assert "no DDS-Security" in line and "full ROS 2 install" in line and "\n" not in line and "/project" not in line
    line = security_problem(RuntimeError("failed to initialize rcl: error not set"),
                            {"ROS_SECURITY_ENABLE": "true", "ROS_SECURITY_STRATEGY": "Enforce"})
    assert "ROS_SECURITY_KEYSTORE is not set" in line
    line = security_problem(RuntimeError("failed to initialize rcl: SECURITY ERROR: directory '/k/enclaves' does not "
                                         "exist., at /project/src/rcl/security.c:202"),
                            {"ROS_SECURITY_ENABLE": "true", "ROS_SECURITY_STRATEGY": "Enforce",
                             "ROS_SECURITY_KEYSTORE": "/k"})
    assert "'/k/enclaves' does not exist" in line and "create_enclave" in line and "security.c" not in line
    # not requested (rcl reads exactly 'true'), or another error: not a security problem
    assert security_problem(err, {"ROS_SECURITY_ENABLE": "TRUE"}) is None
    assert security_problem(ValueError("bad parameter delta"), {"ROS_SECURITY_ENABLE": "true",
                                                                "ROS_SECURITY_KEYSTORE": "/k"}) is None

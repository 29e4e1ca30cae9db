"""Which processes `ros2 run comper_agent bringup` starts, with which arguments (comper_agent.tools.supervisor.plan):
the same nodes as the learner's embedded bring-up, wired by name, each given the parameters its node declares
(a node refuses the others); the supervision itself is tested in test/integration/test_bringup_supervisor.py."""
import os

import pytest

from comper_agent.nodes.run_io import RunDir, default_run_id
from comper_agent.tools.supervisor import main, plan

NOW = 1_800_000_000.0          # the time a default run id is named after


def _names(procs):
    return [(p.name, p.package, p.executable) for p in procs]


def test_comcact_defaults_start_sim_memory_qt_then_the_learner_external():
    procs = plan("comcact_node", ["-p", "total_steps:=100"], now=NOW)
    assert _names(procs) == [("sim_node", "comper_sim", "sim_node"), ("memory_node", "comper_memory", "memory_node"),
                             ("qt_trainer_node", "comper_agent", "qt_trainer_node"),
                             ("comcact_node", "comper_agent", "comcact_node")]
    sim, mem, qt, learner = procs
    run_id = default_run_id("comcact", "InvertedPendulum-v4", 0, now=NOW)
    assert sim.ros_args == ["-p", "env_id:=InvertedPendulum-v4", "-p", f"run_id:={run_id}", "-r", "__node:=sim_node"]
    # the memory's snapshots go beside the learner's checkpoints, as with the embedded bring-up
    assert mem.ros_args == ["-p", f"snapshot_root:={os.path.abspath('runs')}/{run_id}/checkpoints",
                            "-r", "__node:=memory_node"]
    assert "memory_node:=memory_node" in qt.ros_args and "architecture:=comper" not in qt.ros_args
    assert learner.learner and learner.ros_args == ["-p", "total_steps:=100", "-p", "bringup:=external",
                                                    "-p", f"run_id:={run_id}"]
    assert [s for p in procs for s in p.services] == ["/sim_node/step", "/memory_node/store", "/qt_trainer_node/reduce"]


def test_variants_start_only_the_nodes_they_use():
    assert [p.executable for p in plan("comcact_node", ["-p", "algorithm:=ddpg"])] == ["sim_node", "comcact_node"]
    assert [p.executable for p in plan("comper_node", ["-p", "algorithm:=dqn"])] == ["sim_node", "comper_node"]
    assert [p.executable for p in plan("comper_node", ["-p", "algorithm:=comper_f"])] == \
        ["sim_node", "memory_node", "comper_node"]
    assert [p.executable for p in plan("comper_node", ["-p", "reducer:=memory"])] == \
        ["sim_node", "memory_node", "comper_node"]
    comper = plan("comper_node", [])
    assert "architecture:=comper" in comper[2].ros_args and "env_id:=ALE/Freeway-v5" in comper[0].ros_args


def test_node_names_params_file_and_learner_rename(tmp_path):
    f = tmp_path / "p.yaml"
    f.write_text("/**:\n  ros__parameters:\n    algorithm: comcact\n    env_id: Hopper-v4\n"
                 "learner7:\n  ros__parameters:\n    memory_node: mem7\n")
    procs = plan("comcact_node", ["--params-file", str(f), "-p", "sim_node:=/sim7", "-r", "__node:=learner7"], now=NOW)
    assert [p.name for p in procs] == ["sim7", "mem7", "qt_trainer_node", "learner7"]
    run_id = default_run_id("comcact", "Hopper-v4", 0, now=NOW)
    assert procs[0].ros_args[-6:] == ["-p", "env_id:=Hopper-v4", "-p", f"run_id:={run_id}", "-r", "__node:=sim7"]
    assert "memory_node:=mem7" in procs[2].ros_args and procs[1].services == ["/mem7/store"]
    assert "__node:=learner7" not in procs[0].ros_args and procs[3].ros_args[-2:] == ["-r", "__node:=learner7"]


def test_each_process_gets_the_parameters_its_node_declares(tmp_path):
    """A node refuses a parameter that no node of its process declares, so the command line is split: each -p goes to
    the nodes that declare it (seed: the sim and the learner), a params file's values too, its node sections to
    that node only; a -p naming a node (mem7:delta:=...) reaches that node only."""
    f = tmp_path / "p.yaml"
    f.write_text("/**:\n  ros__parameters:\n    total_steps: 300\n    delta: 0.5\n    env_id: Hopper-v4\n"
                 "    bringup: embedded\n    batch_norm: false\n"
                 "mem7:\n  ros__parameters:\n    tm_capacity: 77\n    key_size: 11\n")
    sim, mem, qt, learner = plan("comcact_node", ["--params-file", str(f), "-p", "seed:=4", "-p", "memory_node:=mem7",
                                                  "-p", "mem7:rtm_capacity:=99", "--log-level", "warn"], now=NOW)
    assert sim.ros_args[:5] == ["--log-level", "warn", "-p", "seed:=4", "-p"] and "env_id:=Hopper-v4" in sim.ros_args
    assert mem.ros_args[:10] == ["--log-level", "warn", "-p", "delta:=0.5", "-p", "tm_capacity:=77",
                                 "-p", "key_size:=11", "-p", "mem7:rtm_capacity:=99"]
    assert not any("seed" in a or "total_steps" in a for a in mem.ros_args + qt.ros_args)
    assert qt.ros_args[:2] == ["--log-level", "warn"] and "memory_node:=mem7" in qt.ros_args
    # the file's bringup: embedded is replaced by the bring-up's external (a -p saying embedded is refused)
    assert learner.ros_args[:12] == ["--log-level", "warn", "-p", "total_steps:=300", "-p", "env_id:=Hopper-v4",
                                     "-p", "batch_norm:=false", "-p", "seed:=4", "-p", "memory_node:=mem7"]
    assert "bringup:=embedded" not in learner.ros_args and "bringup:=external" in learner.ros_args
    assert not any("delta" in a or "tm_capacity" in a or "rtm_capacity" in a for a in learner.ros_args)
    # rcl applies the settings in command-line order, the last one winning: so are they passed on
    g = tmp_path / "g.yaml"
    g.write_text("/**:\n  ros__parameters:\n    seed: 7\n")
    sim, *_, learner = plan("comcact_node", ["-p", "seed:=3", "--params-file", str(g)], now=NOW)
    assert [a for a in sim.ros_args if a.startswith("seed")] == ["seed:=3", "seed:=7"]
    assert f"run_id:={default_run_id('comcact', 'InvertedPendulum-v4', 7, now=NOW)}" in learner.ros_args


def test_a_parameter_no_node_declares_is_refused_before_anything_starts(capsys):
    with pytest.raises(ValueError, match="`total_step` is not a parameter of the bring-up's nodes .*did you mean "
                                         "`total_steps`"):
        plan("comcact_node", ["-p", "total_step:=100"])
    # a memory parameter where no memory node runs (DDPG), and one aimed at a node that does not declare it
    with pytest.raises(ValueError, match="`delta` is not a parameter"):
        plan("comcact_node", ["-p", "algorithm:=ddpg", "-p", "delta:=0.5"])
    with pytest.raises(ValueError, match="`delta` is not a parameter"):
        plan("comcact_node", ["-p", "sim_node:delta:=0.5"])
    assert main(["--dry-run", "--ros-args", "-p", "total_step:=100"]) == 2
    assert "`total_step` is not a parameter" in capsys.readouterr().err


def test_the_declared_parameters_are_those_the_nodes_declare():
    """node_parameters (from the config classes) against the nodes: the servers built in this process; the learners'
    node and learner classes (a learner node cannot be built without its servers)."""
    import dataclasses

    import rclpy
    from rclpy.parameter import Parameter

    from comper_agent.nodes.comcact_node import ComcactNode
    from comper_agent.nodes.comper_node import ComperNode
    from comper_agent.nodes.qt_trainer_node import QtTrainerNode
    from comper_agent.tools.bringup_plan import RCLPY_PARAMETERS, learner_config, node_parameters
    from comper_memory.memory_node import MemoryNode
    from comper_sim.sim_node import SimNode
    ctx = rclpy.Context()
    rclpy.init(args=[], context=ctx)
    try:
        for make, name, kw in [(SimNode, "sim_node", {}), (MemoryNode, "memory_node", {}),
                               (QtTrainerNode, "qt_trainer_node", {"architecture": "comcact"}),
                               (QtTrainerNode, "qt_trainer_node", {"architecture": "comper"})]:
            node = make(context=ctx, parameter_overrides=[Parameter(k, value=v) for k, v in kw.items()])
            try:
                assert set(node._parameters) == node_parameters(name, **kw), name
            finally:
                node.destroy_node()
    finally:
        ctx.try_shutdown()
    for cls in (ComcactNode, ComperNode):
        assert {a: learner_config(a) for a in cls.LEARNER_CONFIGS} == cls.LEARNER_CONFIGS
        for algorithm, config in cls.LEARNER_CONFIGS.items():
            assert node_parameters(cls.NODE_NAME, algorithm=algorithm) == RCLPY_PARAMETERS | {
                f.name for c in (cls.CONFIG, config) for f in dataclasses.fields(c)}


def test_the_run_is_decided_up_front_and_the_memory_snapshots_go_into_it(tmp_path):
    """The learner's run directory is known before anything starts: the sim and the learner get its run id, the
    memory node writes its snapshots into its checkpoints/ folder. What the user sets stays theirs."""
    args = ["-p", f"runs_root:={tmp_path}", "-p", "run_id:=r1", "-p", "seed:=3"]
    sim, mem, _, learner = plan("comcact_node", args, now=NOW)
    assert sim.ros_args[-4:-2] == ["-p", "run_id:=r1"]
    assert f"snapshot_root:={tmp_path}/r1/checkpoints" in mem.ros_args
    assert learner.ros_args == [*args, "-p", "bringup:=external"]     # its run_id is the user's
    sim, *_ = plan("comcact_node", ["-p", "seed:=3", "-p", "algorithm:=ddpg"], now=NOW)
    assert f"run_id:={default_run_id('ddpg', 'InvertedPendulum-v4', 3, now=NOW)}" in sim.ros_args
    # checkpoints without the memory: no snapshot_root; the user's own snapshot_root: not replaced
    assert not any("snapshot_root" in a for a in plan("comcact_node", ["-p", "checkpoint_replay:=false"])[1].ros_args)
    mem = plan("comper_node", ["-p", "snapshot_root:=/srv/snaps"])[1]
    assert [a for a in mem.ros_args if "snapshot_root" in a] == ["snapshot_root:=/srv/snaps"]


def _checkpoint(root, run_id, step, replay):
    """A run directory holding one checkpoint of `step` (what plan() reads of it: the run and its replay record)."""
    state = {"run": {"run_id": run_id, "algorithm": "comcact", "env_id": "InvertedPendulum-v4"},
             "counters": {"step": step}, **({"replay": replay} if replay else {})}
    RunDir(root, run_id).save_checkpoint(state, step)
    return root / run_id


def test_a_resume_continues_the_checkpoints_run_and_its_memory_loads_the_saved_snapshot(tmp_path):
    name = "step_000000300.memory"
    run = _checkpoint(tmp_path, "r2", 300, {"kind": "memory", "request": name, "path": "x"})
    (run / "checkpoints" / name).mkdir()
    sim, mem, _, learner = plan("comcact_node", ["-p", f"resume:={run}"])
    assert sim.ros_args[-4:-2] == ["-p", "run_id:=r2"]
    assert mem.ros_args[-6:-2] == ["-p", f"snapshot_root:={run}/checkpoints", "-p", f"snapshot_restore:={name}"]
    assert not any(a.startswith("run_id:=") for a in learner.ros_args)      # the learner takes the checkpoint's
    # a checkpoint without memory contents, or whose snapshot is gone: nothing to load at start-up
    bare = _checkpoint(tmp_path, "r3", 100, None)
    assert not any("snapshot_restore" in a for a in plan("comcact_node", ["-p", f"resume:={bare}"])[1].ros_args)
    (run / "checkpoints" / name).rmdir()
    assert not any("snapshot_restore" in a for a in plan("comcact_node", ["-p", f"resume:={run}"])[1].ros_args)
    with pytest.raises(ValueError, match="resume:=.*no checkpoint at"):
        plan("comcact_node", ["-p", f"resume:={tmp_path / 'none'}"])
    RunDir(tmp_path, "r4").save_checkpoint({"counters": {"step": 1}}, 1)
    with pytest.raises(ValueError, match="resume:=.*the checkpoint has no 'run'"):
        plan("comcact_node", ["-p", f"resume:={tmp_path / 'r4'}"])


@pytest.mark.parametrize("args, message", [
    (["-p", "mode:=async"], "mode:=async is not supported"),
    (["-p", "bringup:=embedded"], "contradicts"),
    (["-p", "algorithm:=dqn"], "comcact_node has no algorithm 'dqn'"),
])
def test_what_the_bring_up_cannot_run_is_one_clear_line(args, message, capsys):
    with pytest.raises(ValueError, match=message):
        plan("comcact_node", args)
    assert main(["--ros-args", *args]) == 2
    assert message in capsys.readouterr().err


def test_dry_run_prints_the_plan(capsys):
    assert main(["--learner", "comcact_node", "--dry-run", "--ros-args", "-p", "algorithm:=ddpg"]) == 0
    out = capsys.readouterr().out.splitlines()
    assert out[0].startswith("sim_node: ros2 run comper_sim sim_node --ros-args -p env_id:=InvertedPendulum-v4 "
                             "-p run_id:=ddpg-InvertedPendulum-v4-s0-")
    assert out[1].startswith("comcact_node: ros2 run comper_agent comcact_node --ros-args -p algorithm:=ddpg "
                             "-p bringup:=external -p run_id:=ddpg-InvertedPendulum-v4-s0-")


def _launch_file():
    from pathlib import Path

    from ament_index_python.packages import get_package_share_directory
    return Path(get_package_share_directory("comper_agent")) / "launch" / "suite.launch.py"


def test_launch_file_is_installed_and_takes_its_nodes_from_the_same_plan():
    """The launch file is for full ROS installs (launch_ros is not on PyPI): here it is checked to be installed,
    valid Python, and built on plan(); its description is built only where launch_ros exists (next test)."""
    import ast
    text = _launch_file().read_text()
    tree = ast.parse(text)
    assert "generate_launch_description" in {n.name for n in tree.body if isinstance(n, ast.FunctionDef)}
    assert "from comper_agent.tools.supervisor import plan" in text


def test_launch_description_builds_where_launch_ros_exists():
    pytest.importorskip("launch_ros", reason="launch_ros is not installed (not on PyPI; full ROS installs only)")
    import importlib.util
    spec = importlib.util.spec_from_file_location("suite_launch", _launch_file())
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    assert module.generate_launch_description().entities

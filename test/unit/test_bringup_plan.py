"""Which processes `ros2 run comper_agent bringup` starts, with which arguments (comper_agent.supervisor.plan):
the same nodes as the learner's embedded bring-up, wired by name; the supervision itself is tested in
test/integration/test_bringup_supervisor.py."""
import pytest

from comper_agent.supervisor import main, plan


def _names(procs):
    return [(p.name, p.package, p.executable) for p in procs]


def test_comcact_defaults_start_sim_memory_qt_then_the_learner_external():
    procs = plan("comcact_node", ["-p", "total_steps:=100"])
    assert _names(procs) == [("sim_node", "comper_sim", "sim_node"), ("memory_node", "comper_memory", "memory_node"),
                             ("qt_trainer_node", "comper_agent", "qt_trainer_node"),
                             ("comcact_node", "comper_agent", "comcact_node")]
    sim, mem, qt, learner = procs
    assert sim.ros_args == ["-p", "total_steps:=100", "-p", "env_id:=InvertedPendulum-v4", "-r", "__node:=sim_node"]
    assert "memory_node:=memory_node" in qt.ros_args and "architecture:=comper" not in qt.ros_args
    assert learner.learner and learner.ros_args == ["-p", "total_steps:=100", "-p", "bringup:=external"]
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
    procs = plan("comcact_node", ["--params-file", str(f), "-p", "sim_node:=/sim7", "-r", "__node:=learner7"])
    assert [p.name for p in procs] == ["sim7", "mem7", "qt_trainer_node", "learner7"]
    assert procs[0].ros_args[-4:] == ["-p", "env_id:=Hopper-v4", "-r", "__node:=sim7"]
    assert "memory_node:=mem7" in procs[2].ros_args and procs[1].services == ["/mem7/store"]
    assert "__node:=learner7" not in procs[0].ros_args and procs[3].ros_args[-2:] == ["-r", "__node:=learner7"]


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
    assert out[0].startswith("sim_node: ros2 run comper_sim sim_node --ros-args -p algorithm:=ddpg")
    assert out[1] == ("comcact_node: ros2 run comper_agent comcact_node --ros-args -p algorithm:=ddpg "
                      "-p bringup:=external")


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
    assert "from comper_agent.supervisor import plan" in text


def test_launch_description_builds_where_launch_ros_exists():
    pytest.importorskip("launch_ros", reason="launch_ros is not installed (not on PyPI; full ROS installs only)")
    import importlib.util
    spec = importlib.util.spec_from_file_location("suite_launch", _launch_file())
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    assert module.generate_launch_description().entities

"""A `-p name:=value` that no node of the process declares stops the node before any work, with the nearest
declared names (rclpy alone would ignore it and run with the default: a misspelt `total_steps` ran comper_node's full
100,000 frames). Every node's real entry point, as `ros2 run` starts it."""
from __future__ import annotations

import pytest
import rclpy
from rclpy.node import Node
from rclpy.parameter import Parameter

from comper_msgs_py.ros_params import UnknownParameter, refuse_undeclared

# (package, executable, the misspelt parameter, what the message suggests)
NODES = [
    ("comper_agent", "comper_node", ("env_id:=CartPole-v1", "total_steps:=1500"), "total_frames"),
    ("comper_agent", "comcact_node", ("total_frame:=1500",), "total_steps"),
    ("comper_agent", "actor_node", ("store_evry:=5",), "store_every"),
    ("comper_agent", "qt_trainer_node", ("reduce_bacth:=5",), "reduce_batch"),
    ("comper_agent", "recorder_node", ("storage_dirr:=x",), None),
    ("comper_memory", "memory_node", ("deltaa:=0.5",), "delta"),
    ("comper_sim", "sim_node", ("env_idd:=Pendulum-v1",), "env_id"),
]


@pytest.mark.parametrize("package,executable,params,suggestion", NODES, ids=[n[1] for n in NODES])
def test_an_undeclared_parameter_stops_the_node_with_a_suggestion(launch, tmp_path, package, executable, params,
                                                                  suggestion):
    args = [a for p in params for a in ("-p", p)]
    proc = launch(package, executable, "--ros-args", "-p", f"runs_root:={tmp_path / 'runs'}", *args,
                  name=f"unknown-{executable}") if executable in ("comper_node", "comcact_node") else \
        launch(package, executable, "--ros-args", *args, name=f"unknown-{executable}")
    try:
        rc = proc.proc.wait(timeout=90)
    except Exception:
        pytest.fail(f"{executable} did not stop:\n{proc.log()}")
    log = proc.log()
    wrong = params[-1].split(":=")[0]
    assert rc == 1, log
    assert f"cannot start" in log and f"`{wrong}` is not a parameter of {executable}" in log, log
    if suggestion:
        assert f"did you mean `{suggestion}`" in log or f"`{suggestion}`?" in log, log
    assert "Traceback" not in log, log
    if executable in ("comper_node", "comcact_node"):        # no run directory left behind
        assert not any((tmp_path / "runs").glob("*")), list((tmp_path / "runs").glob("*"))


def test_a_name_any_node_of_the_process_declares_is_known():
    """The embedded bring-up shares the command line between the learner and the nodes it embeds: a parameter one
    of them declares is not refused by the others, and one that none declares is."""
    context = rclpy.Context()
    rclpy.init(context=context, args=["x", "--ros-args", "-p", "delta:=0.5", "-p", "dleta:=1.0"])
    a = Node("a_node", context=context)
    b = Node("b_node", context=context, parameter_overrides=[Parameter("given", value=1)])
    try:
        b.declare_parameter("delta", 0.1)
        b.declare_parameter("given", 0)
        with pytest.raises(UnknownParameter, match=r"`dleta` is not a parameter of prog; did you mean `delta`\?"):
            refuse_undeclared([a, b], "prog")
        a.declare_parameter("dleta", 0.0)
        refuse_undeclared([a, b], "prog")                  # every name is declared by one of them
    finally:
        a.destroy_node()
        b.destroy_node()
        context.try_shutdown()

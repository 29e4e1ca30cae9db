"""The suite as separate processes with ros2 launch (full ROS 2 installs: launch and launch_ros are not
on PyPI; without them use ``ros2 run comper_agent bringup``, which starts the same processes).

    ros2 launch comper_agent suite.launch.py
    ros2 launch comper_agent suite.launch.py learner:=comper_node env_id:=CartPole-v1
    ros2 launch comper_agent suite.launch.py env_id:=Hopper-v4 total_steps:=50000 seed:=1
    ros2 launch comper_agent suite.launch.py params_file:=src/comper_agent/config/comcact.yaml

Which nodes, with which arguments, is decided by :func:`comper_agent.tools.supervisor.plan`, the same as the
bring-up executable: sim_node, memory_node and qt_trainer_node as the learner variant needs them, then the
learner with ``bringup:=external``. Each node's output is prefixed with its name by launch; Ctrl-C reaches
every node; when any node exits, the launch shuts the others down.
"""
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, OpaqueFunction, Shutdown
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node

ARGUMENTS = {
    "learner": ("comcact_node", "learner node: comcact_node or comper_node"),
    "env_id": ("", "task ('' = the learner's default)"),
    "algorithm": ("", "learner variant ('' = the learner's default)"),
    "total_steps": ("", "comcact_node: agent steps of the run ('' = default)"),
    "seed": ("", "seed of the learner and the simulation ('' = default)"),
    "params_file": ("", "a YAML parameters file given to every node ('' = none)"),
}


def _nodes(context):
    from comper_agent.tools.supervisor import plan
    value = {k: LaunchConfiguration(k).perform(context) for k in ARGUMENTS}
    ros_args = ["--params-file", value["params_file"]] if value["params_file"] else []
    for key in ("env_id", "algorithm", "total_steps", "seed"):
        if value[key]:
            ros_args += ["-p", f"{key}:={value[key]}"]
    return [Node(package=spec.package, executable=spec.executable, name=spec.name, ros_arguments=spec.ros_args,
                 output="screen", emulate_tty=True, on_exit=Shutdown(reason=f"{spec.name} exited"))
            for spec in plan(value["learner"], ros_args)]


def generate_launch_description():
    return LaunchDescription([*(DeclareLaunchArgument(k, default_value=d, description=h)
                                for k, (d, h) in ARGUMENTS.items()),
                              OpaqueFunction(function=_nodes)])

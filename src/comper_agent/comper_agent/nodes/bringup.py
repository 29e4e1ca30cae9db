"""Bring-up helpers shared by the learner nodes (comcact_node, comper_node).

* :class:`Spinner` - each node of a set spun by its own executor in a background thread, so the
  learner loop can run in the main thread and wait on service answers (the clients and their
  blocking calls: :mod:`comper_msgs_py.service_client`).
* :data:`START_HINTS` - how to start each node the learner needs, for the "not available" error.
* :func:`make_embedded_nodes` - the simulation, memory and QT trainer nodes built in this process
  (``bringup:=embedded``): separate node objects that talk to the learner only through ROS.

With ``bringup:=external`` the learner uses nodes started separately with ``ros2 run`` and only
needs their names.
"""
from __future__ import annotations

import threading
from dataclasses import dataclass, field

from rclpy.node import Node
from rclpy.parameter import Parameter

from comper_msgs_py.ros_main import default_executor

__all__ = ["Spinner", "make_embedded_nodes", "EmbeddedNodes", "START_HINTS", "seeded_sampling"]

START_HINTS = {
    "sim": "ros2 run comper_sim sim_node --ros-args -p env_id:=<task> -r __node:={name}",
    "memory": "ros2 run comper_memory memory_node --ros-args -r __node:={name}",
    "qt_trainer": "ros2 run comper_agent qt_trainer_node --ros-args -p memory_node:=<memory> -r __node:={name}",
}


class Spinner:
    """Spins each node with its own executor (:func:`default_executor`) in its own daemon thread,
    so the learner loop can run in the main thread and wait on service futures, and a node that is
    busy in a callback (a QT training) never delays another node's answers."""

    def __init__(self, nodes: list[Node], context):
        self.context = context
        self._pairs: list[tuple] = []
        self._started = False
        self.error: BaseException | None = None
        for n in nodes:
            self.add_node(n)

    def _spin(self, executor) -> None:
        try:
            executor.spin()
        except BaseException as exc:   # context shut down under it, or a callback raised
            self.error = exc

    def add_node(self, node: Node) -> None:
        ex = default_executor(node, self.context)
        ex.add_node(node)
        th = threading.Thread(target=self._spin, args=(ex,), name=f"spin-{node.get_name()}", daemon=True)
        self._pairs.append((ex, th))
        if self._started:
            th.start()

    def start(self) -> "Spinner":
        self._started = True
        for _, th in self._pairs:
            th.start()
        return self

    def stop(self, timeout: float = 5.0) -> None:
        for ex, _ in self._pairs:
            ex.shutdown(timeout_sec=timeout)
        for _, th in self._pairs:
            th.join(timeout)


@dataclass
class EmbeddedNodes:
    sim: Node | None = None
    memory: Node | None = None
    qt_trainer: Node | None = None
    all: list = field(default_factory=list)

    def destroy(self) -> None:
        for n in reversed(self.all):
            try:
                n.destroy_node()
            except Exception:
                pass
        self.all.clear()


def seeded_sampling(memory_params: dict, seed: int, command_line) -> dict:
    """The embedded memory's parameters with its sampling seeded by the run's ``seed`` (so that a lock-step run
    repeats for a fixed seed), unless the command line names ``sample_seed`` (-1 there: OS entropy)."""
    if "sample_seed" in command_line or "sample_seed" in memory_params:
        return memory_params
    return {"sample_seed": seed, **memory_params}


def _overrides(values: dict) -> list[Parameter]:
    return [Parameter(k, value=v) for k, v in values.items()]


def make_embedded_nodes(context, *, sim_name: str, sim_params: dict, memory_name: str | None = None,
                        memory_params: dict | None = None, qt_name: str | None = None,
                        qt_params: dict | None = None) -> EmbeddedNodes:
    """Build the nodes the learner needs in this process (memory and QT trainer only when named).

    Parameters given here win over the command line (they come from the learner's own parameters);
    other command-line parameters (``-p delta:=...``) reach every embedded node that declares them.
    Raises RuntimeError with what to do when a node cannot be built."""
    out = EmbeddedNodes()
    try:
        from comper_sim.sim_node import SimNode
        out.sim = SimNode(sim_name, context=context, parameter_overrides=_overrides(sim_params))
        out.all.append(out.sim)
        if memory_name:
            try:
                from comper_memory.memory_node import MemoryNode
            except ImportError as exc:
                raise RuntimeError(f"the memory node is not importable ({exc}); is comper_memory built "
                                   "(make setup)?") from exc
            out.memory = MemoryNode(memory_name, context=context,
                                    parameter_overrides=_overrides(memory_params or {}))
            out.all.append(out.memory)
        if qt_name:
            from comper_agent.nodes.qt_trainer_node import QtTrainerNode
            out.qt_trainer = QtTrainerNode(qt_name, context=context,
                                           parameter_overrides=_overrides(qt_params or {}))
            out.all.append(out.qt_trainer)
    except BaseException:
        out.destroy()
        raise
    return out

"""Bring-up helpers shared by the learner nodes (COMCACT now, COMPER later).

* :class:`Spinner` - each node of a set spun by its own executor in a background thread, so the
  learner loop can run in the main thread and wait on service futures.
* :func:`call` - a blocking service call from a thread that does not spin (call_async + an
  Event set by the future's done callback); raises :class:`ServiceError` with what to do.
* :func:`wait_for_services` - wait for a set of services, naming the missing ones and how to start them.
* :func:`make_embedded_nodes` - the simulation, memory and QT trainer nodes built in this process
  (``bringup:=embedded``): separate node objects that talk to the learner only through ROS.

With ``bringup:=external`` the learner uses nodes started separately with ``ros2 run`` and only
needs their names.
"""
from __future__ import annotations

import threading
import time
from dataclasses import dataclass, field

from rclpy.node import Node
from rclpy.parameter import Parameter

from comper_msgs_py.ros_main import default_executor

__all__ = ["ServiceError", "Spinner", "PendingCall", "call", "wait_for_services", "make_embedded_nodes",
           "EmbeddedNodes", "START_HINTS"]

START_HINTS = {
    "sim": "ros2 run comper_sim sim_node --ros-args -p env_id:=<task> -r __node:={name}",
    "memory": "ros2 run comper_memory memory_node --ros-args -r __node:={name}",
    "qt_trainer": "ros2 run comper_agent qt_trainer_node --ros-args -p memory_node:=<memory> -r __node:={name}",
}


class ServiceError(RuntimeError):
    """A service call failed: unavailable, timed out, refused (success false) or interrupted."""


class PendingCall:
    """A service call in flight, made from a non-spinning thread (the node is spun elsewhere):
    ``done()`` polls, ``result(timeout)`` waits for the answer."""

    def __init__(self, client, request, what: str | None = None):
        self.client = client
        self.name = what or client.srv_name
        self._done = threading.Event()
        self.future = client.call_async(request)
        self.future.add_done_callback(lambda _f: self._done.set())

    def done(self) -> bool:
        return self._done.is_set()

    def result(self, timeout: float = 60.0, *, check: bool = True):
        """The response; ServiceError on timeout, cancellation, an exception, or (check) success false."""
        name, future = self.name, self.future
        if not self._done.wait(timeout):
            self.client.remove_pending_request(future)
            raise ServiceError(f"{name}: no answer within {timeout:g} s (is the node still running?)")
        if future.cancelled():
            raise ServiceError(f"{name}: the call was cancelled (shutting down?)")
        exc = future.exception()
        if exc is not None:
            raise ServiceError(f"{name}: {type(exc).__name__}: {exc}")
        response = future.result()
        if response is None:
            raise ServiceError(f"{name}: no response (context shut down?)")
        if check and hasattr(response, "success") and not response.success:
            raise ServiceError(f"{name} refused: {response.message}")
        return response


def call(client, request, timeout: float = 60.0, *, what: str | None = None, check: bool = True):
    """Blocking call from a non-spinning thread; the node must be spun by an executor elsewhere.

    check: raise ServiceError when the response has ``success == False`` (with its message)."""
    return PendingCall(client, request, what).result(timeout, check=check)


def wait_for_services(clients: dict, timeout: float, hints: dict | None = None,
                      stop: threading.Event | None = None) -> None:
    """Wait until every client's service is available; raise ServiceError listing the missing ones.

    clients: label -> client; hints: label -> how to start the server."""
    deadline = time.monotonic() + timeout
    pending = dict(clients)
    while pending:
        for label, c in list(pending.items()):
            if c.service_is_ready():
                del pending[label]
        if not pending:
            return
        if time.monotonic() > deadline or (stop is not None and stop.is_set()):
            lines = [f"  {c.srv_name}" + (f"   (start it: {hints[label]})" if hints and label in hints else "")
                     for label, c in pending.items()]
            raise ServiceError(f"services not available after {timeout:g} s:\n" + "\n".join(lines) +
                               "\n(check node names, ROS_DOMAIN_ID and ROS_AUTOMATIC_DISCOVERY_RANGE, "
                               "or use bringup:=embedded)")
        time.sleep(0.05)


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
            from .qt_trainer_node import QtTrainerNode
            out.qt_trainer = QtTrainerNode(qt_name, context=context,
                                           parameter_overrides=_overrides(qt_params or {}))
            out.all.append(out.qt_trainer)
    except BaseException:
        out.destroy()
        raise
    return out

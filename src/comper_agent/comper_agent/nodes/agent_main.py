"""The learner nodes' entry point: ``--help``, signal handling, start-up errors, exit codes.

:func:`run_main` - the first Ctrl-C / SIGTERM finishes the current step, saves a final checkpoint and
exits 0; a second one aborts (130); a node that cannot start logs one ``cannot start: ...`` line
and exits 1. ``--help`` lists the node's parameters and its learner's hyper-parameters.
"""
from __future__ import annotations

import os
import signal
import sys
import threading
from typing import Callable

import rclpy
import rclpy.logging

from comper_msgs_py.params import describe, spec_of
from comper_msgs_py.ros_main import init_ros, security_problem

__all__ = ["run_main", "help_text", "StopRequests"]


def help_text(cls) -> str:
    """A learner node class's --help: its module's usage text and every parameter with its default
    and description."""
    doc = (sys.modules[cls.__module__].__doc__ or "").strip()
    lines = [doc, "", "Node parameters (--ros-args -p name:=value, or --params-file; read-only):"]
    lines += [f"  {f.name} (default {d!r}): {describe(f)}" for f, d, _ in spec_of(cls.CONFIG)]
    if not getattr(cls, "LEARNER_CONFIGS", None):       # actor_node: no learner of its own
        return "\n".join(lines)
    algorithm = {f.name: d for f, d, _ in spec_of(cls.CONFIG)}["algorithm"]
    lcls = cls.LEARNER_CONFIGS[algorithm]
    others = sorted({f"{c.__name__} for {a}" for a, c in cls.LEARNER_CONFIGS.items() if c is not lcls})
    lines += ["", f"Learner hyper-parameters ({lcls.__name__}, algorithm {algorithm}"
              + (f"; {', '.join(others)}" if others else "") + "):"]
    for f, d, _ in spec_of(lcls):
        if f.name != "variant":
            lines.append(f"  {f.name} (default {cls.LEARNER_OVERRIDES.get(f.name, d)!r}): {describe(f)}")
    lines += ["", "In the embedded bring-up, command-line parameters also reach the embedded sim, memory "
              "and QT trainer nodes that declare them (docs/sim.md, docs/memory.md, docs/comcact.md)."]
    return "\n".join(lines)


class StopRequests:
    """Ctrl-C / SIGTERM of a learner process, with a signal handler that takes no lock.

    Python runs a signal handler in the main thread between two bytecodes, wherever that thread is, including
    inside ``threading.Event.set`` or ``Event.wait`` with the event's lock held; a handler that sets an Event can
    then wait for a lock its own thread holds, for ever. That happened when two signals came close together (a
    learner whose supervisor was killed: parent-death SIGTERM, then more): the second handler ran inside the
    first one's ``Event.set``. So :meth:`handler` only flips a flag and writes one byte to a pipe (both safe
    there); a relay thread reads the byte, sets :attr:`stop` and calls ``on_request`` (which may take locks,
    log, set other events). A second signal raises KeyboardInterrupt in the main thread (abort)."""

    def __init__(self, on_request: Callable[[], None]):
        self.requested = False
        self.stop = threading.Event()
        self._on_request = on_request
        self._r, self._w = os.pipe()
        os.set_blocking(self._w, False)
        self._relay = threading.Thread(target=self._run, name="stop-requests", daemon=True)
        self._relay.start()

    def handler(self, signum, _frame) -> None:
        if self.requested:
            raise KeyboardInterrupt
        self.requested = True
        try:
            os.write(self._w, b"s")
        except OSError:         # full (a stop is already on its way) or closed (the process is ending)
            pass

    def _run(self) -> None:
        while os.read(self._r, 1):
            if not self.stop.is_set():
                self.stop.set()
                self._on_request()

    def close(self) -> None:
        """Ends the relay thread. A process keeps it to its end instead: with the handler still installed, a
        late signal writes to the pipe, whose descriptor must not have been reused by then."""
        os.close(self._w)
        self._relay.join(timeout=5.0)
        os.close(self._r)


def run_main(node_cls: type, name: str, args=None) -> int:
    """An agent node's entry point: 0 done (or stopped with Ctrl-C / SIGTERM after saving), 1 cannot
    start / failed, 130 aborted by a second Ctrl-C. ``--help`` prints the parameters."""
    argv = sys.argv if args is None else args
    if "-h" in argv[1:] or "--help" in argv[1:]:
        print(help_text(node_cls))
        return 0
    if not init_ros(args, name):      # discovery range, security: comper_msgs_py.ros_main
        return 1
    logger = rclpy.logging.get_logger(name)
    node = None

    def on_request():       # the relay thread, after the first signal
        if node is not None:
            node.stop_event.set()
        logger.warning("stop requested: finishing the current step, then saving a checkpoint "
                       "(Ctrl-C again to abort)")

    stops = StopRequests(on_request)
    signal.signal(signal.SIGINT, stops.handler)
    signal.signal(signal.SIGTERM, stops.handler)
    rc = 0
    try:
        try:
            node = node_cls()
            if stops.stop.is_set():     # requested while the node was built (on_request saw no node)
                node.stop_event.set()
        except Exception as exc:   # bad parameter, unknown task, missing nodes: one readable message
            logger.error(f"cannot start: {security_problem(exc) or exc}")
            return 1
        rc = node.run()
    except KeyboardInterrupt:
        rc = 130
    finally:
        if node is not None:
            node.shutdown()
        rclpy.try_shutdown()
    return rc

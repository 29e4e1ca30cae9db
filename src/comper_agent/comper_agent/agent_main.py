"""The learner nodes' entry point: ``--help``, signal handling, start-up errors, exit codes.

:func:`run_main` - the first Ctrl-C / SIGTERM finishes the current step, saves a final checkpoint and
exits 0; a second one aborts (130); a node that cannot start logs one ``cannot start: ...`` line
and exits 1. ``--help`` lists the node's parameters and its learner's hyper-parameters.
"""
from __future__ import annotations

import signal
import sys
import threading

import rclpy
from rclpy.signals import SignalHandlerOptions

from comper_msgs_py.params import describe, spec_of

__all__ = ["run_main", "help_text"]


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


def run_main(node_cls: type, name: str, args=None) -> int:
    """An agent node's entry point: 0 done (or stopped with Ctrl-C / SIGTERM after saving), 1 cannot
    start / failed, 130 aborted by a second Ctrl-C. ``--help`` prints the parameters."""
    argv = sys.argv if args is None else args
    if "-h" in argv[1:] or "--help" in argv[1:]:
        print(help_text(node_cls))
        return 0
    rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)
    logger = rclpy.logging.get_logger(name)
    node = None
    stop = threading.Event()

    def on_signal(signum, _frame):
        if stop.is_set():
            raise KeyboardInterrupt
        stop.set()
        if node is not None:
            node.stop_event.set()
        logger.warning("stop requested: finishing the current step, then saving a checkpoint "
                       "(Ctrl-C again to abort)")

    signal.signal(signal.SIGINT, on_signal)
    signal.signal(signal.SIGTERM, on_signal)
    rc = 0
    try:
        try:
            node = node_cls()
            if stop.is_set():
                node.stop_event.set()
        except Exception as exc:   # bad parameter, unknown task, missing nodes: one readable message
            logger.error(f"cannot start: {exc}")
            return 1
        rc = node.run()
    except KeyboardInterrupt:
        rc = 130
    finally:
        if node is not None:
            node.shutdown()
        rclpy.try_shutdown()
    return rc

"""The entry-point loop shared by the suite's service nodes (sim, memory, QT trainer, recorder).

    def main(args=None) -> int:
        return serve_node(SimNode, "sim_node", args)

rclpy.init, construct the node (a failure is one readable `cannot start: ...` line and exit 1,
not a traceback), spin it on the executor chosen for it until Ctrl-C / SIGTERM / shutdown, then
close and destroy it and exit 0.

Signals: rclpy's own signal handlers are not installed (they shut the context down from a
signal-handling thread at an arbitrary moment: with them, a SIGTERM was occasionally ignored, or
the close ran into ``RCLError: context is not valid`` and exited 1). serve_node installs its own
SIGINT / SIGTERM handlers before rclpy.init; a signal only ends the spin loop (the executor
waits at most 0.1 s per round), so ``on_close`` and ``destroy_node`` always run with a valid
context, in the main thread, and the context is shut down last. A signal during construction
stops the node right after it is built. Further signals are ignored (``PR_SET_PDEATHSIG`` can
deliver its SIGTERM more than once; two were seen queued at one recorder). A close that takes
longer than ``close_timeout_s`` is ended by faulthandler's watchdog (a C thread: it works even
when Python is stuck in C), which first writes every thread's stack to stderr; the exit status
is then 1. A signal that arrives before ``main()`` runs (while Python imports the node's
modules) still has the default effect.

``graceful`` is accepted for compatibility: every node now stops this way.
"""
from __future__ import annotations

import faulthandler
import signal
from typing import Callable

import rclpy
from rclpy.executors import Executor, ExternalShutdownException, SingleThreadedExecutor
from rclpy.signals import SignalHandlerOptions

__all__ = ["serve_node", "default_executor"]


def default_executor(node, context=None) -> Executor:
    """The executor a node is spun by: its own ``make_executor(context)`` if it has one (nodes with
    nested service calls need several threads), else a SingleThreadedExecutor (rclpy's
    MultiThreadedExecutor costs ~1.6x per service round trip here: benchmarks/transport_bench.py)."""
    make = getattr(node, "make_executor", None)
    return make(context) if callable(make) else SingleThreadedExecutor(context=context)


def serve_node(make_node: Callable[[], object], name: str, args=None, *,
               executor_for: Callable[[object], Executor] | None = None,
               on_ready: Callable[[object], None] | None = None,
               on_close: Callable[[object], None] | None = None, graceful: bool = False,
               close_timeout_s: float = 60.0) -> int:
    """Run one node as a process: 0 on Ctrl-C / SIGTERM, 1 when it cannot start.

    executor_for(node) makes the executor; by default the node's own ``make_executor()`` if it
    has one (nodes with nested service calls need a multi-threaded one), else a
    SingleThreadedExecutor. on_ready(node) runs before spinning (e.g. torch
    thread settings); on_close(node) after spinning, before destroy_node (e.g. a final flush);
    graceful, close_timeout_s: see the module docstring.
    """
    # a plain flag, not a threading.Event: Event.set takes a lock, and a second signal's handler running inside
    # the first one's Event.set would wait for that lock for ever (the handler runs in the main thread)
    stopping = [False]

    def _stop(*_):
        if not stopping[0]:     # the watchdog is armed once: a repeated signal must not push it back
            stopping[0] = True
            faulthandler.dump_traceback_later(close_timeout_s, exit=True)

    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, _stop)
    rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)
    node = executor = None
    try:
        try:
            node = make_node()
        except Exception as exc:  # bad parameter, unknown env id, unreadable storage: one line
            rclpy.logging.get_logger(name).error(f"cannot start: {type(exc).__name__}: {exc}")
            return 1
        if on_ready is not None:
            on_ready(node)
        executor = executor_for(node) if executor_for is not None else default_executor(node)
        executor.add_node(node)
        while not stopping[0] and rclpy.ok(context=node.context):
            executor.spin_once(timeout_sec=0.1)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        try:
            if executor is not None:
                executor.shutdown(timeout_sec=5.0)
            if node is not None:
                if on_close is not None:
                    on_close(node)
                node.destroy_node()
        finally:
            rclpy.try_shutdown()
            # our handlers stay (a late repeated signal must not kill the exiting process), and so
            # does the watchdog a signal armed: an exit that hangs joining a thread is ended too
    return 0

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

Environment (:func:`init_ros`, also used by the learners' entry point): unless the user chose otherwise,
a node process keeps DDS discovery on its host (``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST``; hosts that
must reach each other set ``SUBNET``), and ``ROS_SECURITY_ENABLE=true`` means Enforce (rcl's own default,
Permissive, would run without security when the keystore is missing). Security that is requested but
cannot be in force (no keystore or enclave, or a DDS without DDS-Security, as the PyPI wheels' Fast DDS)
is one ``cannot start: ...`` line and exit 1 (docs/security.md).
"""
from __future__ import annotations

import faulthandler
import os
import re
import signal
import warnings
from typing import Callable

import rclpy
import rclpy.logging
from rclpy.executors import Executor, ExternalShutdownException, SingleThreadedExecutor
from rclpy.signals import SignalHandlerOptions

from .ros_params import refuse_undeclared

__all__ = ["serve_node", "default_executor", "init_ros", "apply_env_defaults", "security_problem"]

#: where DDS discovery looks when the user has not said (ROS_AUTOMATIC_DISCOVERY_RANGE, ROS_LOCALHOST_ONLY)
DEFAULT_DISCOVERY_RANGE = "LOCALHOST"
_SECURITY_DOC = "docs/security.md"


def apply_env_defaults(environ=os.environ) -> dict[str, str]:
    """Set the suite's defaults for a node process where the user has not chosen (before rclpy.init,
    which reads them): ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST unless it or the older ROS_LOCALHOST_ONLY
    is set; with ROS_SECURITY_ENABLE=true, ROS_SECURITY_STRATEGY=Enforce unless set. What it set."""
    out = {}
    if not environ.get("ROS_AUTOMATIC_DISCOVERY_RANGE") and not environ.get("ROS_LOCALHOST_ONLY"):
        out["ROS_AUTOMATIC_DISCOVERY_RANGE"] = DEFAULT_DISCOVERY_RANGE
    if environ.get("ROS_SECURITY_ENABLE") == "true" and not environ.get("ROS_SECURITY_STRATEGY"):
        out["ROS_SECURITY_STRATEGY"] = "Enforce"
    environ.update(out)
    return out


def security_problem(exc: BaseException, environ=os.environ) -> str | None:
    """Why requested ROS 2 security cannot be in force, in one line, from the error of rclpy.init or of
    the first node; None when security is not requested (ROS_SECURITY_ENABLE is not 'true', as rcl reads
    it) or the error is about something else."""
    if environ.get("ROS_SECURITY_ENABLE") != "true":
        return None
    text = re.sub(r",? at /\S+:\d+", "", " ".join(str(exc).split()))     # one line, no C source locations
    low = text.lower()
    strategy = environ.get("ROS_SECURITY_STRATEGY") or "Permissive"
    keystore = environ.get("ROS_SECURITY_KEYSTORE", "")
    head = f"ROS 2 security is requested (ROS_SECURITY_ENABLE=true, ROS_SECURITY_STRATEGY={strategy}) but"
    tail = f"; unset ROS_SECURITY_ENABLE to run without it ({_SECURITY_DOC})"
    if "security libraries" in low or "dsecurity" in low:
        return (f"{head} this ROS 2 install's DDS has no DDS-Security (the Fast DDS of the PyPI wheels is built "
                f"without it): SROS2 enclaves need a full ROS 2 install{tail}")
    if strategy == "Enforce" and not keystore:
        return (f"{head} ROS_SECURITY_KEYSTORE is not set: point it at a keystore made with `ros2 security "
                f"create_keystore` that holds this node's enclave{tail}")
    if "security" in low:
        return (f"{head} the keystore {keystore!r} cannot be used ({text}): create the enclave with `ros2 security "
                f"create_enclave <keystore> /<enclave>` and start the node with --ros-args --enclave /<enclave>"
                f"{tail}")
    return None


def init_ros(args=None, name: str = "node") -> bool:
    """rclpy.init for an entry point, after :func:`apply_env_defaults`, without rclpy's signal handlers.
    False, after one ``cannot start: ...`` line, when it fails (bad arguments, requested security that
    cannot be in force); a warning when security is requested but Permissive runs without it."""
    apply_env_defaults()
    log = rclpy.logging.get_logger(name)
    if os.environ.get("ROS_SECURITY_ENABLE") == "true":
        # rclpy's clean-up after a node that security kept from being created; the cause is logged
        warnings.filterwarnings("ignore", message="Failed to fini rosout publisher", category=RuntimeWarning)
    try:
        rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)
    except Exception as exc:
        log.error("cannot start: " + (security_problem(exc) or " ".join(f"{type(exc).__name__}: {exc}".split())))
        return False
    keystore = os.environ.get("ROS_SECURITY_KEYSTORE", "")
    if os.environ.get("ROS_SECURITY_ENABLE") == "true" and os.environ.get("ROS_SECURITY_STRATEGY") != "Enforce" \
            and not os.path.isdir(os.path.join(keystore, "enclaves")):
        log.warning(f"ROS 2 security is requested but NOT in force: no keystore at ROS_SECURITY_KEYSTORE={keystore!r}, "
                    "and ROS_SECURITY_STRATEGY=Permissive runs without it (unset that variable, or set it to Enforce, "
                    f"to refuse to start instead; {_SECURITY_DOC})")
    return True


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
    if not init_ros(args, name):
        return 1
    node = executor = None
    try:
        try:
            node = make_node()
            refuse_undeclared([node], name)     # a misspelt -p would otherwise run with the default
        except Exception as exc:  # bad or unknown parameter, unknown env id, unreadable storage: one line
            rclpy.logging.get_logger(name).error(
                f"cannot start: {security_problem(exc) or f'{type(exc).__name__}: {exc}'}")
            if node is not None:
                node.destroy_node()
                node = None
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

"""Shared test set-up: ROS isolation and helpers to run nodes as real separate processes.

Every test session gets its own ROS_DOMAIN_ID and localhost-only discovery, so parallel runs and
other ROS processes on the machine do not cross-talk. Child processes inherit both.
"""
from __future__ import annotations

import os
import random
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

os.environ.setdefault("ROS_DOMAIN_ID", str(random.SystemRandom().randint(1, 100)))
os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
os.environ.setdefault("OMP_NUM_THREADS", "1")


def ros2_command() -> str:
    exe = shutil.which("ros2")
    if exe is None:
        pytest.fail("no ros2 command on PATH: run the tests through `make test` (it sources env.sh)")
    return exe


class NodeProcess:
    """A node started with `ros2 run` in its own process group; output goes to a log file."""

    def __init__(self, package: str, executable: str, *args: str, log_dir: Path, name: str | None = None,
                 prefix: tuple = (), env: dict | None = None):
        """prefix: a command put in front (e.g. ``ip netns exec <ns>``); env: variables set on top of ours."""
        self.name = name or executable
        self.log_path = log_dir / f"{self.name}.log"
        self._log = open(self.log_path, "wb")
        self.proc = subprocess.Popen([*prefix, ros2_command(), "run", package, executable, *args],
                                     stdout=self._log, stderr=subprocess.STDOUT,
                                     start_new_session=True, env={**os.environ, **(env or {})})

    def log(self) -> str:
        self._log.flush()
        return self.log_path.read_text(errors="replace")

    def alive(self) -> bool:
        return self.proc.poll() is None

    def kill(self, sig=signal.SIGKILL) -> None:
        if self.proc.poll() is None:
            try:
                os.killpg(self.proc.pid, sig)
            except ProcessLookupError:
                pass
        try:
            self.proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            os.killpg(self.proc.pid, signal.SIGKILL)
            self.proc.wait(timeout=10)

    def stop(self) -> int | None:
        """SIGINT (what Ctrl-C sends), then SIGKILL if it does not exit within 10 s."""
        if self.proc.poll() is None:
            os.killpg(self.proc.pid, signal.SIGINT)
            try:
                self.proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                self.kill()
        self._log.close()
        return self.proc.returncode


@pytest.fixture
def launch(tmp_path):
    """launch(package, executable, *args) -> NodeProcess; every process is stopped at teardown."""
    started: list[NodeProcess] = []

    def _launch(package: str, executable: str, *args: str, name: str | None = None, prefix: tuple = (),
                env: dict | None = None) -> NodeProcess:
        p = NodeProcess(package, executable, *args, log_dir=tmp_path, name=name, prefix=prefix, env=env)
        started.append(p)
        return p

    yield _launch
    for p in started:
        p.stop()


@pytest.fixture
def ros_node():
    """An rclpy context and a client node in this test process, shut down afterwards."""
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node

    context = rclpy.Context()
    rclpy.init(context=context)
    node = Node(f"test_client_{os.getpid()}_{int(time.time() * 1000) % 100000}", context=context)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    node.test_executor = executor  # spin with spin_once(node) / call(...), never the global executor
    try:
        yield node
    finally:
        executor.shutdown()
        node.destroy_node()
        context.try_shutdown()


def spin_once(node, timeout: float = 0.1) -> None:
    """Process one callback of the test node (its own executor and context)."""
    node.test_executor.spin_once(timeout_sec=timeout)


def call(node, client, request, timeout: float = 30.0, resend_s: float = 2.0):
    """Call a service from the test thread, spinning `node` until the response (or fail).

    A store, sample or stats request without an answer after resend_s seconds is sent again, as MemoryClient
    does, through the same loop (service_client.resend_until_answered; the first call of a new client can lose
    its answer while the server's side of discovery completes, docs/memory-service.md "Lost answers and
    re-sends"); a store without a request id gets a fresh one first, so the memory applies it once. Other
    requests are sent once."""
    if not client.wait_for_service(timeout_sec=timeout):
        pytest.fail(f"service {client.srv_name} did not appear within {timeout} s")
    from comper_msgs.srv import GetStats, Sample, Store
    from comper_msgs_py.service_client import abandon_future, resend_until_answered
    # requests whose repetition is harmless: a store the memory recognises by its request id, and reads
    resend = isinstance(request, (Store.Request, Sample.Request, GetStats.Request))
    if resend and hasattr(request, "request_id") and not request.request_id:
        from comper_memory.client import new_request_id
        request.request_id = new_request_id()

    def spin(futures, seconds):
        end = time.monotonic() + seconds
        while not any(f.done() for f in futures) and (left := end - time.monotonic()) > 0:
            node.test_executor.spin_once(timeout_sec=min(left, 0.05))

    answered, futures = resend_until_answered(lambda: client.call_async(request), spin,
                                              lambda future: abandon_future(client, future), timeout,
                                              resend_s if resend else 0.0)
    if answered is None:
        pytest.fail(f"service {client.srv_name} did not answer within {timeout} s (sent {len(futures)} time(s))")
    return answered.result()

"""RecordingLink: a learner node's link to the recorder_node that bags its run (``record:=true``).

The recorder runs as a child process (``record_process:=child``, the default: its work runs on
another core; it gets SIGTERM when the agent dies, even by SIGKILL) or as a node on the agent's
executor (``in_process``). The link starts it, waits until it has subscribed to every recorded
topic (the first episode must not be published before), applies flow control (the agent waits
while ``record_window`` episodes are not yet in the bag; ``RecordingFlow``) and, at the end, hands
every published message over before it stops the recorder. Topics and QoS: docs/recording.md.
"""
from __future__ import annotations

import ctypes
import functools
import json
import os
import signal
import subprocess
import sys
import time

__all__ = ["RecordingLink", "record_topics"]


def record_topics(node_fqn: str, sim_node: str, memory_node: str | None) -> list[str]:
    """The topics record:=true bags: the learner's contract topics, the sim's episodes, memory stats."""
    topics = [f"{node_fqn}/transitions", f"{node_fqn}/episodes", f"{node_fqn}/evaluations",
              f"/{sim_node.strip('/')}/episodes"]
    if memory_node:
        topics.append(f"/{memory_node.strip('/')}/stats")
    return topics


class RecordingLink:
    """node: the learner node (it publishes the recorded topics); p: its AgentRunConfig; run_dir:
    its run_io.RunDir; topics: :func:`record_topics`. Construct before the node's executor threads
    start (a child process is forked then); call :meth:`wait_subscribed` once they run."""

    def __init__(self, node, p, run_id: str, run_dir, topics: list[str]):
        self.node, self.p, self.run_dir, self.topics = node, p, run_dir, topics
        self.log = node.get_logger()
        self.recorder = None          # in-process RecorderNode
        self.proc = None              # child process
        self.flow = None
        params = {"run_id": run_id, "algorithm": p.algorithm, "output_dir": str(run_dir.path.parent),
                  "storage": p.record_storage, "compression": p.record_compression, "topics": topics}
        if p.record_process == "in_process":
            from rclpy.parameter import Parameter

            from comper_agent.recording.recorder_node import RecorderNode
            self.recorder = RecorderNode(context=node.context, parameter_overrides=[
                Parameter(k, value=v) for k, v in params.items()])
            self.name = self.recorder.get_fully_qualified_name()
        else:
            self._start_process(params)
        from comper_agent.recording.recorder_node import RecordingFlow
        self.flow = RecordingFlow(node, self.name, window=p.record_window, timeout_s=p.record_wait_s)

    @property
    def nodes(self) -> list:
        """Nodes to spin in this process (the in-process recorder)."""
        return [self.recorder] if self.recorder is not None else []

    def _start_process(self, params: dict) -> None:
        self._subscribers_before = {t: self.node.count_subscribers(t) for t in self.topics}
        self.name = f"/{self.node.get_name()}_recorder"     # no namespace given: at the root
        cmd = [sys.executable, "-m", "comper_agent.recording.recorder_node", "--ros-args", "-r", f"__node:={self.name[1:]}"]
        for k, v in params.items():
            cmd += ["-p", f"{k}:={json.dumps(v)}"]   # JSON is YAML: strings stay strings, lists lists
        self.log_path = self.run_dir.file("recorder.log")
        with open(self.log_path, "ab") as log:
            # own session: a terminal's Ctrl-C reaches the agent only, which hands over and stops the
            # recorder; PR_SET_PDEATHSIG: the recorder gets SIGTERM when the agent dies (even SIGKILL)
            self.proc = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, env=os.environ.copy(),
                                         start_new_session=True,
                                         preexec_fn=functools.partial(_die_with_parent, os.getpid()))

    def wait_subscribed(self) -> None:
        """Return once the recorder process has subscribed to every recorded topic."""
        if self.proc is None:
            return
        before = self._subscribers_before
        deadline = time.monotonic() + self.p.startup_timeout_s
        while any(self.node.count_subscribers(t) <= before[t] for t in self.topics):
            rc = self.proc.poll()
            if rc is not None:
                tail = self.log_path.read_text(errors="replace")[-2000:]
                raise RuntimeError(f"the recorder process exited with {rc} before subscribing; {self.log_path}:\n{tail}")
            if time.monotonic() > deadline:
                raise RuntimeError(f"the recorder process did not subscribe to {self.topics} within "
                                   f"startup_timeout_s={self.p.startup_timeout_s:g} s (see {self.log_path})")
            time.sleep(0.02)
        self.log.info(f"recording into {self.run_dir.path / 'bag'} by a recorder process (pid "
                      f"{self.proc.pid}, log {self.log_path})")

    def wait_window(self, topics: list[str], stop) -> float:
        """Flow control before publishing an episode: wait while record_window episodes are not yet
        in the bag. Returns the seconds waited. A dead recorder process ends the recording."""
        if self.flow is None:
            return 0.0
        if self.proc is not None and self.proc.poll() is not None:
            self.log.error(f"the recorder process ended with {self.proc.returncode}; this run is no longer "
                           f"recorded (see {self.log_path})")
            self.flow = None
            return 0.0
        waited, ok = self.flow.wait(*topics, stop=stop)   # Ctrl-C is not held up
        if not ok:
            self.log.warning(f"the recorder has not written {self.p.record_window} or more of this run's episodes "
                             f"for record_wait_s={self.p.record_wait_s:g} s; they are written off (the bag may "
                             f"miss them) and training goes on")
        return waited

    def sent(self, topic: str) -> None:
        if self.flow is not None:
            self.flow.sent(topic)

    def stop(self, publishing_nodes: list) -> None:
        """Hand every message over and stop the recorder: a child process once each of its topics'
        publishers has its messages acknowledged (reliable QoS), then SIGINT (it takes what it still
        holds and closes the bag); an in-process recorder closes its bag and is destroyed."""
        proc, self.proc = self.proc, None
        if proc is not None:
            from comper_msgs_py.qos import wait_acknowledged
            topics = set(self.topics)
            nodes = publishing_nodes if proc.poll() is None else []   # a dead recorder acknowledges nothing
            wait_acknowledged([pub for node in nodes for pub in node.publishers if pub.topic_name in topics], 5.0,
                              each=True)
            proc.send_signal(signal.SIGINT)
            try:
                rc = proc.wait(timeout=30.0)
            except Exception:
                proc.kill()
                rc = proc.wait()
            if rc != 0:
                self.log.error(f"the recorder process ended with {rc}; see {self.log_path}")

    def close_in_process(self) -> None:
        """After the executors stopped: close the in-process recorder's bag and destroy it."""
        rec, self.recorder = self.recorder, None
        if rec is not None:
            try:
                rec.close()
            finally:
                rec.destroy_node()


try:   # loaded here, not in the forked child (no imports between fork and exec)
    _LIBC = ctypes.CDLL(None, use_errno=True) if sys.platform.startswith("linux") else None
except OSError:
    _LIBC = None


def _die_with_parent(parent_pid: int) -> None:
    """preexec_fn of the recorder process: SIGTERM when the parent (the agent) dies (Linux prctl).
    A parent that died between fork and prctl sends nothing: then the child exits here (the
    documented race of PR_SET_PDEATHSIG)."""
    if _LIBC is not None:
        _LIBC.prctl(1, int(signal.SIGTERM))   # PR_SET_PDEATHSIG = 1
        if os.getppid() != parent_pid:
            os._exit(1)

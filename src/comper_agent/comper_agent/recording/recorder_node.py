"""recorder_node: records the agents' episode topics into a crash-safe rosbag2 bag.

    ros2 run comper_agent recorder_node --ros-args -p run_id:=hopper-s0 -p algorithm:=comcact
    ros2 run comper_agent recorder_node --ros-args --params-file src/comper_agent/config/recorder.yaml

Subscriptions use rclpy's serialized path (``raw=True``): the CDR bytes go straight into the bag,
nothing is deserialised. The bag is written by :class:`comper_agent.recording.bags.ChunkedBagWriter`
(MCAP by default, sqlite3 as an option, zstd-compressed by default, split files closed every
``max_file_duration_s``), so a SIGKILL loses at most the last few seconds. See docs/recording.md.

In-process use (an agent node with a ``record`` parameter)::

    from comper_agent.recording.recorder_node import RecorderNode
    recorder = RecorderNode(context=self.context, parameter_overrides=[
        Parameter("run_id", value=run_id), Parameter("algorithm", value="comcact"),
        Parameter("topics", value=[f"/{self.get_name()}/transitions", ...])])
    executor.add_node(recorder)          # any executor; its callbacks are mutually exclusive
    ...
    recorder.close(); recorder.destroy_node()
"""
from __future__ import annotations

import importlib
import json
import os
import signal
import sys
import threading
import time
from pathlib import Path

import rclpy
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from rclpy.node import Node
from rclpy.qos import (DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy)

from comper_msgs_py.qos import RECORDED_QOS
from comper_msgs_py.ros_main import serve_node
from comper_msgs_py.ros_params import declare_config

from comper_agent.recording.bags import (ChunkedBagWriter, RecorderConfig, comper_typestore, make_qos,
                        parse_topic_spec)

__all__ = ["RecorderNode", "RecordingFlow", "EPISODE_QOS", "STATUS_QOS", "main",
           "run_directory"]

#: QoS of <agent>/transitions, <agent>/episodes, <agent>/evaluations (docs/architecture.md)
EPISODE_QOS = RECORDED_QOS
#: QoS of <recorder>/status: the latest count is all that matters, and a late subscriber gets it
STATUS_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1, reliability=ReliabilityPolicy.RELIABLE,
                        durability=DurabilityPolicy.TRANSIENT_LOCAL)


def _msg_class(msgtype: str):
    pkg, _, name = msgtype.split("/")
    return getattr(importlib.import_module(f"{pkg}.msg"), name)


def run_directory(output_dir: str, run_id: str, bag_name: str = "bag") -> Path:
    """<output_dir>/<run_id>/<bag_name>, or bag_name_1, _2, ... when that exists and is not empty."""
    base = Path(output_dir) / run_id
    cand = base / bag_name
    k = 0
    while cand.exists() and any(cand.iterdir()):
        k += 1
        cand = base / f"{bag_name}_{k}"
    return cand


class RecorderNode(Node):
    """Records topics into ``<output_dir>/<run_id>/<bag_name>``. ``node_kwargs`` go to rclpy's Node
    (context, parameter_overrides, namespace, ...)."""

    def __init__(self, node_name: str = "recorder_node", **node_kwargs):
        super().__init__(node_name, **node_kwargs)
        try:
            self.config: RecorderConfig = declare_config(self, RecorderConfig)
            c = self.config
            self.run_id = c.run_id or time.strftime("%Y%m%d-%H%M%S")
            self.bag_path = run_directory(c.output_dir, self.run_id, c.bag_name)
            custom = {"run_id": self.run_id, "algorithm": c.algorithm,
                      "recorder": json.dumps({"storage": c.storage, "compression": c.compression,
                                              "max_file_size_mb": c.max_file_size_mb,
                                              "max_file_duration_s": c.max_file_duration_s}),
                      "started_unix_s": f"{time.time():.3f}"}
            self.writer = ChunkedBagWriter(
                self.bag_path, storage=c.storage, compression=c.compression, typestore=comper_typestore(),
                max_file_size_bytes=int(c.max_file_size_mb * 2**20),
                max_file_duration_s=c.max_file_duration_s, fsync=c.fsync, custom_data=custom)
        except Exception:
            super().destroy_node()
            raise
        self._lock = threading.Lock()
        self._closed = False
        self._group = MutuallyExclusiveCallbackGroup()
        from comper_msgs.msg import RecorderStatus
        self._status_msg = RecorderStatus(bag_path=str(self.bag_path))
        self._status_pub = self.create_publisher(RecorderStatus, "~/status", STATUS_QOS)
        self._status_sent = 0.0      # monotonic time of the last ~/status
        self._status_dirty = True
        self._subs: dict[str, object] = {}
        self._handles: dict[str, int] = {}        # topic -> bag writer handle
        self._pending: dict[str, str | None] = {}   # topic -> msgtype (None: to discover)
        for spec in c.topics:
            name, msgtype = parse_topic_spec(spec)
            name = self.resolve_topic_name(name)
            self._pending[name] = msgtype
        self._subscribe_known()
        period = min(0.25, c.max_file_duration_s / 4) if c.max_file_duration_s > 0 else 1.0
        self._split_timer = self.create_timer(max(period, 0.02), self._on_timer, callback_group=self._group)
        self._discovery_timer = (self.create_timer(c.discovery_period_s, self._discover, callback_group=self._group)
                                 if self._pending else None)
        self.get_logger().info(
            f"recording {len(self._subs)} topic(s) into {self.bag_path} ({c.storage}, compression "
            f"{c.compression}, split every "
            f"{c.max_file_duration_s:g} s or {c.max_file_size_mb:g} MB); waiting for "
            f"{sorted(self._pending) or 'none'}")

    # subscriptions -------------------------------------------------------------------------
    def _qos_for(self, name: str, msgtype: str) -> tuple[QoSProfile, list]:
        """Reliable for the contract's reliable topics; best effort (matches any publisher) for
        gauges such as memory_node/stats; adapted to the publishers' offers when discovered."""
        depth = self.config.qos_depth
        infos = self.get_publishers_info_by_topic(name)
        if infos:
            reliable = all(i.qos_profile.reliability == ReliabilityPolicy.RELIABLE for i in infos)
            transient = all(i.qos_profile.durability == DurabilityPolicy.TRANSIENT_LOCAL for i in infos)
        else:
            reliable = not msgtype.endswith("/MemoryStats")
            transient = False
        qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=depth,
                         reliability=ReliabilityPolicy.RELIABLE if reliable else ReliabilityPolicy.BEST_EFFORT,
                         durability=DurabilityPolicy.TRANSIENT_LOCAL if transient else DurabilityPolicy.VOLATILE)
        return qos, [make_qos(reliable, depth, transient)]

    def _subscribe(self, name: str, msgtype: str) -> None:
        qos, offered = self._qos_for(name, msgtype)
        handle = self.writer.add_topic(name, msgtype, offered)
        self._handles[name] = handle
        cls = _msg_class(msgtype)
        self._subs[name] = self.create_subscription(
            cls, name, lambda data, h=handle: self._on_message(h, data), qos,
            callback_group=self._group, raw=True)
        self._pending.pop(name, None)
        self.get_logger().info(f"recording {name} [{msgtype}]")

    def _subscribe_known(self) -> None:
        for name, msgtype in list(self._pending.items()):
            if msgtype is not None:
                self._subscribe(name, msgtype)

    def _discover(self) -> None:
        if not self._pending:
            if self._discovery_timer is not None:
                self._discovery_timer.cancel()
            return
        for name, types in self.get_topic_names_and_types():
            if name in self._pending and types:
                try:
                    self._subscribe(name, types[0])
                except Exception as exc:
                    self.get_logger().error(f"cannot record {name} [{types[0]}]: {exc}")
                    self._pending.pop(name, None)

    # writing -------------------------------------------------------------------------------
    def _on_message(self, handle: int, data: bytes) -> None:
        with self._lock:
            if not self._closed:
                self.writer.write(handle, time.time_ns(), data)
                self._status_dirty = True
                if time.monotonic() - self._status_sent >= self.config.status_period_s:
                    self._publish_status()

    def _on_timer(self) -> None:
        with self._lock:
            if not self._closed and self.writer.due():
                self.writer.split()
            if self._status_dirty and not self._closed:
                self._publish_status()

    def _publish_status(self, closed: bool = False) -> None:
        """~/status: messages written per topic (under self._lock)."""
        s, m = self.writer.stats, self._status_msg
        m.header.stamp = self.get_clock().now().to_msg()
        m.topics = list(s.topic_counts)
        m.messages = [int(v) for v in s.topic_counts.values()]
        m.bytes = int(s.bytes)
        m.closed = bool(closed)
        try:
            self._status_pub.publish(m)
        except Exception:   # a shut-down context (close after Ctrl-C): nobody to tell
            pass
        self._status_sent, self._status_dirty = time.monotonic(), False

    def flush(self) -> None:
        """Close the open bag file now (everything received so far becomes durable)."""
        with self._lock:
            if not self._closed:
                self.writer.split()

    @property
    def messages_recorded(self) -> int:
        return self.writer.stats.messages

    def drain(self) -> int:
        """Write what the subscriptions hold but the executor has not dispatched yet (messages that
        arrived just before a stop); returns how many."""
        n = 0
        for name, sub in list(self._subs.items()):
            while True:
                try:
                    with sub.handle:
                        got = sub.handle.take_message(sub.msg_type, sub.raw)
                except Exception:   # destroyed handle or shut-down context: nothing more to take
                    break
                if got is None:
                    break
                self._on_message(self._handles[name], got[0])
                n += 1
        return n

    def close(self) -> None:
        """Take the messages still queued, then close the bag (idempotent). Call before destroy_node."""
        drained = self.drain() if not self._closed else 0
        with self._lock:
            if self._closed:
                return
            self._closed = True
            self.writer.close()
            self._publish_status(closed=True)
        s = self.writer.stats
        self.get_logger().info(
            f"bag closed: {self.bag_path} ({s.messages} messages, {s.bytes / 2**20:.1f} MB, "
            f"{s.files_closed} file(s); per topic {s.topic_counts}; {drained} taken at close)")

    def destroy_node(self):
        self.close()
        return super().destroy_node()


class RecordingFlow:
    """Credit-based flow control on the recording contract, for a publisher of recorded topics.

    The contract's topics are reliable KEEP_LAST 100 (EPISODE_QOS): a publisher that runs more than 100
    messages ahead of the recorder's writes loses the oldest (the writer's or the reader's history
    overwrites them). The recorder reports what it has written on ``<recorder>/status``; ``wait`` blocks
    while ``window`` or more of this publisher's messages on a topic are sent but not yet written::

        flow = RecordingFlow(node, "/comcact_node_recorder", window=50, timeout_s=60.0)
        waited_s, ok = flow.wait(topic)      # before publishing
        pub.publish(msg); flow.sent(topic)

    The counts are this publisher's own: only it publishes on the topics it controls, and the recorder
    subscribed before its first message. A wait that times out (recorder stuck, dead or missing
    messages) writes the backlog off, so the next wait starts from zero instead of timing out again;
    a closed bag ends all waiting. ``status`` subscriptions run on the node's executor, so ``wait``
    must be called from another thread (an agent's training loop)."""

    def __init__(self, node: Node, recorder: str, *, window: int, timeout_s: float):
        from comper_msgs.msg import RecorderStatus
        if window < 1:
            raise ValueError(f"window must be >= 1, not {window}")
        self.window, self.timeout_s = int(window), float(timeout_s)
        self._cond = threading.Condition()
        self._sent: dict[str, int] = {}
        self._written: dict[str, int] = {}
        self._floor: dict[str, int] = {}     # sent count at a write-off: those are not waited for again
        self.closed = False
        self.timeouts = 0
        self.status_topic = f"{recorder.rstrip('/')}/status"
        self._sub = node.create_subscription(RecorderStatus, self.status_topic, self._on_status, STATUS_QOS)

    def _on_status(self, msg) -> None:
        with self._cond:
            for t, n in zip(msg.topics, msg.messages):
                self._written[t] = max(self._written.get(t, 0), int(n))
            self.closed = self.closed or bool(msg.closed)
            self._cond.notify_all()

    def sent(self, topic: str, n: int = 1) -> None:
        with self._cond:
            self._sent[topic] = self._sent.get(topic, 0) + int(n)

    def backlog(self, topic: str) -> int:
        """Messages sent on `topic` that the recorder has not reported written (nor been written off)."""
        with self._cond:
            return self._backlog(topic)

    def _backlog(self, topic: str) -> int:
        return self._sent.get(topic, 0) - max(self._written.get(topic, 0), self._floor.get(topic, 0))

    def wait(self, *topics: str, stop: threading.Event | None = None) -> tuple[float, bool]:
        """Block until every topic's backlog is below the window, or `stop` is set; (seconds waited,
        False if it timed out)."""
        t0 = None
        with self._cond:
            while not self.closed and not (stop is not None and stop.is_set()):
                over = [t for t in topics if self._backlog(t) >= self.window]
                if not over:
                    break
                now = time.monotonic()
                if t0 is None:
                    t0 = now
                if now - t0 >= self.timeout_s:
                    for t in over:
                        self._floor[t] = self._sent.get(t, 0)
                    self.timeouts += 1
                    return now - t0, False
                self._cond.wait(min(self.timeout_s - (now - t0), 0.1 if stop is not None else float("inf")))
        return (time.monotonic() - t0 if t0 is not None else 0.0), True


def main(args=None) -> int:
    """Entry point of ``ros2 run comper_agent recorder_node``: 0 on Ctrl-C / SIGTERM."""
    argv = sys.argv if args is None else args
    if "-h" in argv[1:] or "--help" in argv[1:]:
        print(__doc__)
        print("Parameters (--ros-args -p name:=value):")
        from comper_msgs_py.params import describe, spec_of
        for f, default, _ in spec_of(RecorderConfig):
            print(f"  {f.name} (default {default!r}): {describe(f)}")
        return 0
    import faulthandler
    faulthandler.register(signal.SIGUSR1, all_threads=True)   # kill -USR1 <pid>: every thread's stack to stderr
    return serve_node(RecorderNode, "recorder_node", args, on_close=lambda node: node.close(), graceful=True)


if __name__ == "__main__":
    sys.exit(main())

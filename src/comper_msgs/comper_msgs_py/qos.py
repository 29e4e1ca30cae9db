"""QoS profiles of the suite's topics, defined once (docs/recording.md gives the contract).

RECORDED_QOS: the topics a run is recorded from (``<agent>/episodes``, ``<agent>/evaluations``,
``<agent>/transitions``, ``<sim>/episodes``): reliable, keep-last 100, volatile. Reliable so that a
recorder gets every episode; keep-last 100 lets a slow or briefly busy subscriber catch up on a
burst (step_many with autoreset can end many short episodes in one call) without unbounded memory;
volatile because recorders start before the run (a late joiner does not need past episodes).

SERVICE_QOS: every service of the suite, on the server (its request reader and response writer) and on
the clients (``comper_msgs_py.service_client``; request writer and response reader): reliable,
volatile, keep-last SERVICE_DEPTH. A service has one response writer for all its clients, and a
reliable keep-last writer drops its oldest sample when its history is full, acknowledged or not: with
rclpy's default depth 10 (and the memory node's earlier 100), a burst of answers to other clients (the
rate limiter's retries) could push out an answer that a busy client had not acknowledged yet, and that
answer was never delivered. The deep history keeps every answer until it is acknowledged in all but
pathological cases, and the depth bounds memory (keep-all would block the server's write instead once
its resource limits are reached). Requests: a burst from many learners waits while a long call runs.
"""
from __future__ import annotations

from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

__all__ = ["RECORDED_QOS", "RECORDED_DEPTH", "SERVICE_QOS", "SERVICE_DEPTH"]

RECORDED_DEPTH = 100
RECORDED_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=RECORDED_DEPTH,
                          reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.VOLATILE)

SERVICE_DEPTH = 1000
SERVICE_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=SERVICE_DEPTH,
                         reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.VOLATILE)

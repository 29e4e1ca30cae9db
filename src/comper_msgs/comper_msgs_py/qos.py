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

import time

from rclpy.duration import Duration
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

__all__ = ["RECORDED_QOS", "RECORDED_DEPTH", "SERVICE_QOS", "SERVICE_DEPTH", "HAND_OVER_S", "wait_acknowledged"]

RECORDED_DEPTH = 100
RECORDED_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=RECORDED_DEPTH,
                          reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.VOLATILE)

SERVICE_DEPTH = 1000
SERVICE_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=SERVICE_DEPTH,
                         reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.VOLATILE)


#: a node's hand-over at its end: the longest wait, in all, for the matched subscribers of its result topics
#: to acknowledge its last messages before its publishers are destroyed (the learners' and the actors')
HAND_OVER_S = 3.0


def wait_acknowledged(publishers, timeout_s: float, *, each: bool = False) -> bool:
    """Waits until every matched reliable subscriber of each publisher has acknowledged what it published,
    at most `timeout_s` in all (each=True: per publisher). A publisher with no matched subscriber is done at
    once; a destroyed publisher or a shut-down context has nothing to hand over. True when all were in time."""
    deadline = time.monotonic() + timeout_s
    ok = True
    for pub in publishers:
        left = timeout_s if each else max(0.0, deadline - time.monotonic())
        try:
            ok = pub.wait_for_all_acked(Duration(nanoseconds=int(left * 1e9))) and ok
        except Exception:
            continue
    return ok

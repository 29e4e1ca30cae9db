"""QoS profiles of the suite's topics, defined once (docs/recording.md gives the contract).

RECORDED_QOS: the topics a run is recorded from (``<agent>/episodes``, ``<agent>/evaluations``,
``<agent>/transitions``, ``<sim>/episodes``): reliable, keep-last 100, volatile. Reliable so that a
recorder gets every episode; keep-last 100 lets a slow or briefly busy subscriber catch up on a
burst (step_many with autoreset can end many short episodes in one call) without unbounded memory;
volatile because recorders start before the run (a late joiner does not need past episodes).
"""
from __future__ import annotations

from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

__all__ = ["RECORDED_QOS", "RECORDED_DEPTH"]

RECORDED_DEPTH = 100
RECORDED_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=RECORDED_DEPTH,
                          reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.VOLATILE)

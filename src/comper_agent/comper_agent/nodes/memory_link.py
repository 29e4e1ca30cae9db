"""MemoryLink: a learner node's side of the compact memory, through the suite's public clients.

It holds the :class:`~comper_memory.client.MemoryClient` (store, sample, stats), the
:class:`~comper_memory.client.ReductionClient` of the reducer (the QT trainer, or the memory node
for COMPER-F) and the subscription to the QT trainer's ``qt_model``, and it keeps what the learner
needs between calls: the RTM and TM sizes, the update batches prefetched from the current RTM, the
updated batches waiting to be stored again with fresh labels (``restore_batch``), the reduction in
flight (``reduce_overlap``) and the newest QT model. *When* to store, reduce and how
many batches to fetch is the pure schedule of :mod:`comper_agent.core.memory_schedule`.
"""
from __future__ import annotations

import threading
import time
from typing import Callable

from comper_memory.client import MemoryClient, MemoryServiceError, ReductionClient, ReduceReply
from comper_msgs.msg import QTModel as QTModelMsg
from comper_msgs_py.arrays import Transitions
from comper_msgs_py.service_client import PendingCall

from comper_agent.core.memory_schedule import batches_per_sample
from comper_agent.nodes.qt_trainer_node import QT_MODEL_QOS, msg_to_qt

__all__ = ["MemoryLink"]


class MemoryLink:
    """node: the learner node (spun in another thread once the run starts); p: its AgentRunConfig
    (memory_node, qt_trainer_node, service_timeout_s, prefetch_batches, reduce_overlap, reduce_batch,
    qt_epochs, qt_wait_s); reducer: 'qt_trainer' or 'memory'; uses_qt: subscribe to the QT model;
    timers: the node's run_io.PhaseTimers; on_reduced(reply): called after each reduction's answer
    that :meth:`collect` finishes (a node may set it later)."""

    def __init__(self, node, p, *, reducer: str, uses_qt: bool, timers, device: str | None = "cpu",
                 on_reduced: Callable[[ReduceReply], None] | None = None):
        self.p, self.reducer, self.timers, self.device = p, reducer, timers, device
        self.log = node.get_logger()
        self.on_reduced = on_reduced
        mem = p.memory_node.strip("/")
        self.memory = MemoryClient(node, f"/{mem}", timeout=p.service_timeout_s)
        server = p.qt_trainer_node.strip("/") if reducer == "qt_trainer" else mem
        self.reduction = ReductionClient(node, f"/{server}", timeout=p.service_timeout_s)
        self.qt = None                       # newest QTModel received on qt_model
        self.qt_cond = threading.Condition()
        self.qt_received = 0
        # async learners (comcact_node mode:=async) send their re-stores in calls of their own, marked relabel,
        # so the memory's rate limiter does not count them as environment steps; lock step sends one call
        self.relabel_apart = False
        if uses_qt:
            node.create_subscription(QTModelMsg, f"/{p.qt_trainer_node.strip('/')}/qt_model",
                                     self._on_qt_model, QT_MODEL_QOS)
        self.reset()

    def reset(self) -> None:
        self.rtm_size = 0
        self.tm_sets = 0
        self.reductions = 0
        self.last_reduce: dict = {}
        self.sample_calls = 0
        self.prefetched: list = []            # (batch, counts) drawn from the current RTM, next last
        self.restore: list[Transitions] = []   # restore_batch: updated batches with fresh labels, not yet stored
        self.restored = 0                      # transitions stored again so far
        self.in_flight: PendingCall | None = None   # reduce_overlap: the reduction sent and not yet answered

    def services(self) -> dict:
        """label -> rclpy client, for wait_for_services."""
        out = {"memory": self.memory.store_client()}
        if self.reducer == "qt_trainer":
            out["qt_trainer"] = self.reduction.reduce_client()
        return out

    # --- QT model ------------------------------------------------------------------------------
    def _on_qt_model(self, msg: QTModelMsg) -> None:
        try:
            t0 = time.perf_counter()
            model = msg_to_qt(msg, device=self.device)
            self.timers.add("qt_model_rebuild", time.perf_counter() - t0)
        except Exception as exc:
            self.log.error(f"cannot rebuild the published QTModel v{msg.version}: {exc}")
            return
        with self.qt_cond:
            if self.qt is None or model.version >= self.qt.version:
                self.qt = model
            self.qt_received += 1
            self.qt_cond.notify_all()

    def qt_model(self):
        """The newest QT model (None before the first one arrived)."""
        with self.qt_cond:
            return self.qt

    def qt_predictions(self, batch: Transitions):
        """QT(tau) for `batch`'s rows from the local copy of the newest QTModel (timed as 'qt_predict'); None
        before the first one arrived."""
        qt = self.qt_model()
        if qt is None:
            return None
        from comper_memory.core import transition_keys
        with self.timers("qt_predict"):
            return qt.predict_transitions(batch, transition_keys)

    @property
    def qt_version(self) -> int:
        return self.qt.version if self.qt is not None else 0

    def wait_qt_model(self, version: int) -> None:
        """Wait up to qt_wait_s for the QTModel of `version` to arrive on qt_model."""
        deadline = time.monotonic() + self.p.qt_wait_s
        with self.qt_cond:
            while (self.qt is None or self.qt.version < version) and time.monotonic() < deadline:
                self.qt_cond.wait(max(0.0, deadline - time.monotonic()))

    # --- store / sample / stats ------------------------------------------------------------------
    def store(self, t: Transitions | None, with_restore: bool = True) -> None:
        """One store call (timed as 'memory'): `t` (new labelled transitions, or None) and, with_restore,
        the re-stored batches waiting (:meth:`queue_restore`); nothing when there is neither. With
        relabel_apart the re-stores go in a second call marked relabel (not counted by a rate limiter)."""
        new = [t] if t is not None else []
        restore = self.restore if with_restore else []
        if not new and not restore:
            return
        if with_restore:
            self.restored += sum(len(x) for x in restore)
            self.restore = []
        calls = [(new, False), (restore, True)] if self.relabel_apart else [(new + restore, False)]
        with self.timers("memory"):
            for parts, relabel in calls:
                if parts:
                    self.memory.store(parts[0] if len(parts) == 1 else Transitions.concatenate(parts),
                                      relabel=relabel)

    def queue_restore(self, batch: Transitions) -> None:
        """restore_batch: `batch` (an update's batch, labelled after that update) goes out again with
        the next store call that takes the re-stores (Algorithm 7 / thesis 4.1.1)."""
        self.restore.append(batch)

    def stats(self) -> dict:
        d = self.memory.stats()
        self.rtm_size, self.tm_sets = d["rtm_size"], d["tm_sets"]
        return d

    def next_batch(self, k: int, source: str, updates_left: int):
        """(batch, counts) for the next update: a prefetched one, or one sample call that draws the
        batches of the updates before the next reduction (:func:`batches_per_sample`). None when the
        memory refuses (fewer entries than k: evictions, TM drained); the caller refreshes its sizes.
        A reduction drops what is left (the RTM changed)."""
        if self.prefetched:
            return self.prefetched.pop()
        n = batches_per_sample(source, self.p.prefetch_batches, updates_left)
        with self.timers("memory"):
            try:
                t, _, counts = self.memory.sample(int(k), source, num_batches=n)
            except MemoryServiceError:
                return None
        self.sample_calls += 1
        if n == 1:
            return t, counts
        self.prefetched = [(t.take(slice(i * k, (i + 1) * k)), counts[i * k:(i + 1) * k])
                           for i in reversed(range(n))]
        return self.prefetched.pop()

    # --- reductions ------------------------------------------------------------------------------
    def _send(self) -> PendingCall:
        return self.reduction.send(int(self.p.reduce_batch), int(self.p.qt_epochs))

    def reduce(self) -> ReduceReply:
        """One blocking reduction (reduce_batch sets, qt_epochs)."""
        return self._finish(self._send())

    def start_overlapped(self) -> bool:
        """reduce_overlap: wait for the reduction in flight (if any), send the next one and return True
        (the caller goes on learning). False = reduce synchronously (overlap off, or RTM still empty)."""
        self.collect(wait=True)           # at most one in flight
        if not self.p.reduce_overlap or self.rtm_size == 0:
            return False
        self.in_flight = self._send()
        return True

    def collect(self, wait: bool) -> ReduceReply | None:
        """Finish the overlapped reduction if it has answered (wait: block until it has); its reply or
        None. Calls on_reduced(reply)."""
        pending = self.in_flight
        if pending is None or not (wait or pending.done()):
            return None
        self.in_flight = None
        with self.timers("reduce_wait" if not pending.done() else "reduce_collect"):
            r = self._finish(pending)
        if self.on_reduced is not None:
            self.on_reduced(r)
        return r

    def _finish(self, pending: PendingCall) -> ReduceReply:
        r = self.reduction.reply(pending)
        self.prefetched.clear()     # drawn from the RTM this reduction changed: not used
        self.timers.add("qt_server" if self.reducer == "qt_trainer" else "memory_reduce_server", r.duration_s, 0)
        self.rtm_size = r.rtm_size
        self.reductions += 1
        self.last_reduce = {"sets": r.sets_reduced, "qt_version": r.qt_version,
                            "qt_loss": r.qt_loss, "duration_s": r.duration_s, "message": r.message}
        return r

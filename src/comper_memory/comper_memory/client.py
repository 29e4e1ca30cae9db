"""MemoryClient: numpy in, numpy out access to a running ``memory_node`` for any rclpy learner.

Two ways to use it:

(a) **Embedded** in a learner node that some executor spins in another thread (the common
    pattern: the learner's main loop in the main thread, a ``MultiThreadedExecutor`` spinning
    the node in a background thread)::

        node = rclpy.create_node("learner")
        executor = MultiThreadedExecutor(); executor.add_node(node)
        threading.Thread(target=executor.spin, daemon=True).start()
        memory = MemoryClient(node, "memory_node")
        memory.wait_for_service(10.0)
        memory.store(transitions)

    Calls block the *calling* thread on a ``threading.Event`` until the executor thread
    delivers the response; they never spin. So do not call from a callback of a
    single-threaded executor that also spins this node (it would wait for itself: a
    deadlock that ends in ``TimeoutError``); from callbacks use a ``MultiThreadedExecutor``
    and put the client in a different (or reentrant) callback group (``callback_group=``).

(b) **Standalone**: ``MemoryClient.standalone("memory_node")`` creates its own context (unless
    one is given), node and background executor thread; ``close()`` (or ``with``) tears them
    down::

        with MemoryClient.standalone("memory_node") as memory:
            memory.wait_for_service(10.0)
            ids = memory.store(transitions).identity_ids

Errors (``comper_msgs_py.service_client``): a request the node refuses raises
:class:`MemoryServiceError` (a ``ServiceRefused``) carrying the node's message (nothing was changed
by the refused call); no answer within the timeout raises ``ServiceTimeout`` (a ``TimeoutError``);
a node that is not spun by any executor raises ``RuntimeError`` at once.
Conversions go through :mod:`comper_msgs_py.convert` only (no per-element work).

:class:`ReductionClient` calls the ``<reducer>/reduce`` service that both the memory node (labels
as predictions) and the QT trainer (QT's predictions) serve.
"""
from __future__ import annotations

import os
import time
from dataclasses import dataclass

import numpy as np

from comper_msgs.msg import MemoryStats
from comper_msgs.srv import GetStats, Reduce, ReduceBegin, ReduceCommit, Sample, Snapshot, Store
from comper_msgs_py.arrays import Transitions
from comper_msgs_py.convert import batch_to_transitions, numpy_to_seq, seq_to_numpy, transitions_to_batch
from comper_msgs_py.service_client import PendingCall, ServiceClient, ServiceRefused, ServiceTimeout

from .core.results import ReductionLease

__all__ = ["MemoryClient", "ReductionClient", "MemoryServiceError", "RateLimitTimeout", "StoreReply", "ReductionSets",
           "new_request_id",
           "ReduceReply", "CommitReply", "SOURCES", "STATS_FIELDS", "stats_to_dict"]

SOURCES = {"rtm": Sample.Request.SOURCE_RTM, "tm": Sample.Request.SOURCE_TM}
#: the MemoryStats fields, in the message's order (the message definition is their one source)
STATS_FIELDS = tuple(k for k in MemoryStats.get_fields_and_field_types() if k != "header")


def new_request_id() -> int:
    """A store's request id: random 63 bits (never 0), unique across clients and processes in practice.
    Give the same id to :meth:`MemoryClient.store` again to retry a store safely: the memory answers a
    repeated id from its remembered answer and never applies the batch twice (``resend_window``)."""
    return int.from_bytes(os.urandom(8), "little") >> 1 or 1


def stats_to_dict(msg: MemoryStats) -> dict:
    """A MemoryStats message as {field: int | float} (every field but the header)."""
    out = {}
    for k in STATS_FIELDS:
        v = getattr(msg, k)
        out[k] = float(v) if isinstance(v, float) else int(v)
    return out


class MemoryServiceError(ServiceRefused):
    """The memory node refused a request (success=false); ``message`` is the node's reason."""


class RateLimitTimeout(ServiceTimeout):
    """A store or sample was held back by the node's rate limiter for longer than the client's
    rate_limit_timeout; the message says which limit (nothing was stored or drawn)."""


@dataclass
class StoreReply:
    identity_ids: np.ndarray   # uint64 [N]: identity each transition joined or created
    new_identities: int        # transitions that created a new identity
    stored: int                # transitions stored (= N)
    wal_sequence: int          # durable operation number (0 when the node has no storage_dir)


#: what reduce_begin returns: the memory core's own lease type (one definition)
ReductionSets = ReductionLease


@dataclass
class ReduceReply:
    sets_reduced: int
    rtm_size: int
    duration_s: float
    message: str
    qt_version: int = 0      # the QT trainer's model version after this reduction (0: memory node)
    qt_loss: float = float("nan")

    @classmethod
    def from_response(cls, r) -> "ReduceReply":
        return cls(int(r.sets_reduced), int(r.rtm_size), float(r.duration_s), r.message, int(r.qt_version),
                   float(r.qt_loss))


@dataclass
class CommitReply:
    committed: int
    rtm_size: int
    message: str


class MemoryClient(ServiceClient):
    """Client of one memory node (services ``<memory_node>/store`` etc.).

    node: an rclpy node spun by an executor in another thread (see the module docstring), or
    ``MemoryClient.standalone(memory_node)``. memory_node: the memory node's name, or its fully
    qualified name ('/ns/memory_node'); a relative name resolves in this node's namespace.
    timeout: default seconds per call (each method also takes ``timeout=``).
    rate_limit_timeout: how long store and sample keep retrying a call that the node's rate limiter
    holds back (``rate_limited`` in the answer) before they raise :class:`RateLimitTimeout`
    (None = ``timeout``); retries back off from 1 ms to 50 ms.
    resend_s: a store, sample, stats or snapshot request whose answer has not come after this many seconds
    is sent again (0 = never; then one lost answer costs the whole ``timeout``; a first call right after the
    node comes up can lose its answer while discovery completes). Safe: every store carries a fresh request
    id, and the node answers a re-sent one with the first one's answer without applying it twice
    (``resend_window``); a snapshot save or restore carries a request id too and is carried out once (the node
    remembers its last 64 answers); a re-sent sample is just another draw, a re-sent stats request another read.
    ``resent`` counts them.
    """

    REFUSED = MemoryServiceError
    NODE_NAME = "memory_client"

    def __init__(self, node, memory_node: str = "memory_node", *, timeout: float = 30.0,
                 rate_limit_timeout: float | None = None, resend_s: float = 2.0, callback_group=None):
        super().__init__(node, memory_node, timeout=timeout, callback_group=callback_group)
        self.resend_s = float(resend_s)
        self.memory_node = self.server
        self.rate_limit_timeout = timeout if rate_limit_timeout is None else float(rate_limit_timeout)
        self.rate_limited_waits = 0     # calls of this client that had to wait for the rate limiter
        self.rate_limited_s = 0.0       # seconds they waited in all
        self._store = self._make(Store, "store")
        self._sample = self._make(Sample, "sample")
        self._reduce = self._make(Reduce, "reduce")
        self._begin = self._make(ReduceBegin, "reduce_begin")
        self._commit = self._make(ReduceCommit, "reduce_commit")
        self._stats = self._make(GetStats, "get_stats")
        self._snapshot = self._make(Snapshot, "snapshot")

    @classmethod
    def standalone(cls, memory_node: str = "memory_node", context=None, *, node_name: str | None = None,
                   timeout: float = 30.0, rate_limit_timeout: float | None = None,
                   resend_s: float = 2.0) -> "MemoryClient":
        """A client with its own node and a background executor thread (``close()`` or ``with``
        tears them down). context=None: a private rclpy context is created and shut down by
        ``close()``; a given context must already be initialised and is left running."""
        return super().standalone(memory_node, context, node_name=node_name, timeout=timeout,
                                  rate_limit_timeout=rate_limit_timeout, resend_s=resend_s)

    def store_client(self):
        """The rclpy client of ``<memory_node>/store`` (for :func:`wait_for_services`)."""
        return self._store

    def _call_limited(self, client, request, timeout: float | None):
        """_call (re-sent when its answer is lost), retried while the node's rate limiter holds it back."""
        r = self._call(client, request, timeout, check=False, resend_s=self.resend_s)
        if r.success or not r.rate_limited:
            return self._call_checked(client, r)
        t0 = time.monotonic()
        deadline, pause = t0 + self.rate_limit_timeout, 0.001
        self.rate_limited_waits += 1
        try:
            while True:
                if time.monotonic() + pause > deadline:
                    raise RateLimitTimeout(f"{client.srv_name}: held back by the rate limiter for "
                                           f"{self.rate_limit_timeout:g} s: {r.message}")
                time.sleep(pause)
                pause = min(2 * pause, 0.05)
                r = self._call(client, request, timeout, check=False, resend_s=self.resend_s)
                if r.success or not r.rate_limited:
                    return self._call_checked(client, r)
        finally:
            self.rate_limited_s += time.monotonic() - t0

    def _call_checked(self, client, response):
        if not response.success:
            raise self.REFUSED(client.srv_name, response.message)
        return response

    # --- the memory's operations --------------------------------------------------------------
    def store(self, transitions: Transitions, *, timeout: float | None = None,
              request_id: int | None = None, relabel: bool = False) -> StoreReply:
        """Store N transitions (value_labels required, one per transition); a refused batch stores nothing.
        Waits while the node's rate limiter holds it back (``rate_limit_timeout``); sent again with the same
        request id when its answer is lost (``resend_s``), so it is applied once. request_id: None = a new
        one (:func:`new_request_id`); a caller that retries a store after a ServiceTimeout passes the id of
        the first try, so the memory applies the batch at most once. relabel: these transitions were
        stored once already and go again with fresh value labels (``restore_batch``); the node's rate
        limiter neither holds them back nor counts them as inserts."""
        req = Store.Request(request_id=new_request_id() if request_id is None else int(request_id),
                            relabel=bool(relabel))
        transitions_to_batch(transitions, req.batch)
        r = self._call_limited(self._store, req, timeout)
        return StoreReply(seq_to_numpy(r.identity_ids, np.uint64), int(r.new_identities), int(r.stored),
                          int(r.wal_sequence))

    def sample(self, k: int, source: str = "rtm", seed: int | None = None, *,
               num_batches: int = 1, timeout: float | None = None) -> tuple[Transitions, np.ndarray, np.ndarray]:
        """k distinct entries, uniformly, from RTM (default) or TM (the COMPER-M ablation).

        Returns (transitions, identity_ids uint64 [n], counts uint32 [n]) with n = k * num_batches
        (num_batches independent draws of k, one after the other); transitions.value_labels are QT
        predictions (RTM) or newest labels (TM). seed >= 0: a reproducible draw. Waits while the
        node's rate limiter holds it back (``rate_limit_timeout``)."""
        if source not in SOURCES:
            raise ValueError(f"sample: source must be 'rtm' or 'tm', got {source!r}")
        req = Sample.Request(batch_size=int(k), source=SOURCES[source], seed=-1 if seed is None else int(seed),
                             num_batches=int(num_batches))
        r = self._call_limited(self._sample, req, timeout)
        return (batch_to_transitions(r.batch, validate=False), seq_to_numpy(r.identity_ids, np.uint64),
                seq_to_numpy(r.counts, np.uint32))

    def reduce(self, max_sets: int = 0, *, timeout: float | None = None) -> ReduceReply:
        """One-call reduction on the memory node (prediction = each set's newest label);
        max_sets 0 = the node's reduce_batch."""
        return ReduceReply.from_response(self._call(self._reduce, Reduce.Request(max_sets=int(max_sets)), timeout))

    def reduce_begin(self, max_sets: int = 0, *, timeout: float | None = None) -> ReductionSets:
        """Phase 1: lease up to max_sets (0 = reduce_batch) oldest TM sets."""
        r = self._call(self._begin, ReduceBegin.Request(max_sets=int(max_sets)), timeout)
        s = r.sets
        return ReductionSets(int(s.reduction_id), seq_to_numpy(s.identity_ids, np.uint64),
                             batch_to_transitions(s.representatives, validate=False),
                             seq_to_numpy(s.label_history, np.float32),
                             seq_to_numpy(s.history_lengths, np.uint32), seq_to_numpy(s.counts, np.uint32))

    def reduce_commit(self, reduction_id: int, identity_ids, predictions, *,
                      timeout: float | None = None) -> CommitReply:
        """Phase 2: upsert the lease's identities into RTM with one prediction each."""
        req = ReduceCommit.Request(reduction_id=int(reduction_id))
        req.identity_ids = numpy_to_seq(np.asarray(identity_ids), np.uint64)
        req.predictions = numpy_to_seq(np.asarray(predictions), np.float32)
        r = self._call(self._commit, req, timeout)
        return CommitReply(int(r.committed), int(r.rtm_size), r.message)

    def stats(self, *, timeout: float | None = None) -> dict:
        """The node's MemoryStats as a dict (keys as in comper_msgs/msg/MemoryStats)."""
        return stats_to_dict(self._call(self._stats, GetStats.Request(), timeout, resend_s=self.resend_s).stats)

    def snapshot(self, path: str = "", *, timeout: float | None = None) -> tuple[str, int]:
        """Save a verified snapshot: '' = the node's storage_dir (checkpoint + WAL rotation), a
        relative name = under the node's snapshot_root, an absolute path only inside it (paths are
        on the node's machine; anything else is refused). Returns (path written, wal_sequence)."""
        return self._snapshot_call(Snapshot.Request.OP_SAVE, path, timeout)

    def restore(self, path: str = "", *, timeout: float | None = None) -> tuple[str, int]:
        """Replace the node's state by the snapshot at `path` ('' = storage_dir's snapshot, else
        confined to snapshot_root like :meth:`snapshot`); a corrupted or incompatible snapshot,
        a path outside snapshot_root or a node with snapshot_service other than save_restore
        raises MemoryServiceError and leaves the state untouched."""
        return self._snapshot_call(Snapshot.Request.OP_RESTORE, path, timeout)

    def _snapshot_call(self, op: int, path: str, timeout: float | None) -> tuple[str, int]:
        """Sent again after ``resend_s`` without an answer, with the same fresh request id: the node answers a
        re-send from the first call's answer and does not save or restore twice."""
        request = Snapshot.Request(op=op, path=str(path), request_id=new_request_id())
        r = self._call(self._snapshot, request, timeout, resend_s=self.resend_s)
        return r.path, int(r.wal_sequence)


class ReductionClient(ServiceClient):
    """Client of a ``<reducer>/reduce`` service: the QT trainer's (QT trains on the popped sets and
    predicts their targets) or the memory node's (each set's newest label). ``send`` starts a
    reduction and returns at once (the caller may go on learning: ``reduce_overlap``); ``reply``
    waits for its answer."""

    def __init__(self, node, reducer: str, *, timeout: float = 120.0, callback_group=None):
        super().__init__(node, reducer, timeout=timeout, callback_group=callback_group)
        self._reduce = self._make(Reduce, "reduce")

    def reduce_client(self):
        """The rclpy client of ``<reducer>/reduce`` (for :func:`wait_for_services`)."""
        return self._reduce

    def send(self, max_sets: int = 0, epochs: int = 0) -> PendingCall:
        """Start one reduction (max_sets / epochs 0 = the server's reduce_batch / qt_epochs)."""
        return self._send(self._reduce, Reduce.Request(max_sets=int(max_sets), epochs=int(epochs)))

    def reply(self, pending: PendingCall, timeout: float | None = None) -> ReduceReply:
        """The answer of a reduction started by :meth:`send`."""
        wait = self.timeout if timeout is None else float(timeout)
        return ReduceReply.from_response(pending.result(wait, stop=self.stop))

    def reduce(self, max_sets: int = 0, epochs: int = 0, *, timeout: float | None = None) -> ReduceReply:
        """One blocking reduction."""
        return self.reply(self.send(max_sets, epochs), timeout)

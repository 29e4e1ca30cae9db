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

Errors: a request the node refuses raises :class:`MemoryServiceError` carrying the node's
message (nothing was changed by the refused call); no answer within the timeout raises
``TimeoutError``; a node that is not spun by any executor raises ``RuntimeError`` at once.
Conversions go through :mod:`comper_msgs_py.convert` only (no per-element work).
"""
from __future__ import annotations

import threading
import time
from dataclasses import dataclass

import numpy as np

from comper_msgs.srv import GetStats, Reduce, ReduceBegin, ReduceCommit, Sample, Snapshot, Store
from comper_msgs_py.arrays import Transitions
from comper_msgs_py.convert import batch_to_transitions, numpy_to_seq, seq_to_numpy, transitions_to_batch

__all__ = ["MemoryClient", "MemoryServiceError", "StoreReply", "ReductionSets", "ReduceReply",
           "CommitReply", "SOURCES"]

SOURCES = {"rtm": Sample.Request.SOURCE_RTM, "tm": Sample.Request.SOURCE_TM}
_STATS_FIELDS = ("key_size", "delta", "identities", "tm_sets", "rtm_size", "transitions_stored",
                 "similarity_hits", "hit_rate", "compaction_ratio", "reductions", "sets_reduced",
                 "evictions", "bytes_used", "wal_sequence")


class MemoryServiceError(RuntimeError):
    """The memory node refused a request (success=false); ``message`` is the node's reason."""

    def __init__(self, service: str, message: str):
        super().__init__(f"{service}: {message}")
        self.service = service
        self.message = message


@dataclass
class StoreReply:
    identity_ids: np.ndarray   # uint64 [N]: identity each transition joined or created
    new_identities: int        # transitions that created a new identity
    stored: int                # transitions stored (= N)
    wal_sequence: int          # durable operation number (0 when the node has no storage_dir)


@dataclass
class ReductionSets:
    """Phase 1 of a two-phase reduction (the sets leased to a QT trainer)."""
    reduction_id: int
    identity_ids: np.ndarray     # uint64 [M]
    representatives: Transitions  # [M]; value_labels = newest label of each set
    label_history: np.ndarray    # float32, concatenated histories, oldest first
    history_lengths: np.ndarray  # uint32 [M]
    counts: np.ndarray           # uint32 [M]

    def __len__(self) -> int:
        return int(self.identity_ids.shape[0])

    def histories(self) -> list[np.ndarray]:
        """One float32 array per set, oldest label first."""
        if not len(self):
            return []
        return np.split(self.label_history, np.cumsum(self.history_lengths.astype(np.int64))[:-1])


@dataclass
class ReduceReply:
    sets_reduced: int
    rtm_size: int
    duration_s: float
    message: str


@dataclass
class CommitReply:
    committed: int
    rtm_size: int
    message: str


class MemoryClient:
    """Client of one memory node (services ``<memory_node>/store`` etc.).

    node: an rclpy node spun by an executor in another thread (see the module docstring).
    memory_node: the memory node's name, or its fully qualified name ('/ns/memory_node');
    a relative name resolves in this node's namespace.
    timeout: default seconds per call (each method also takes ``timeout=``).
    """

    def __init__(self, node, memory_node: str = "memory_node", *, timeout: float = 30.0,
                 callback_group=None):
        self.node = node
        self.memory_node = memory_node.rstrip("/")
        self.timeout = float(timeout)
        self._owned = None  # (context_owned, executor, thread) for standalone clients

        def make(srv_type, name):
            return node.create_client(srv_type, f"{self.memory_node}/{name}", callback_group=callback_group)

        self._store = make(Store, "store")
        self._sample = make(Sample, "sample")
        self._reduce = make(Reduce, "reduce")
        self._begin = make(ReduceBegin, "reduce_begin")
        self._commit = make(ReduceCommit, "reduce_commit")
        self._stats = make(GetStats, "get_stats")
        self._snapshot = make(Snapshot, "snapshot")
        self._clients = (self._store, self._sample, self._reduce, self._begin, self._commit,
                         self._stats, self._snapshot)

    # --- construction -------------------------------------------------------------------------
    @classmethod
    def standalone(cls, memory_node: str = "memory_node", context=None, *, node_name: str | None = None,
                   timeout: float = 30.0) -> "MemoryClient":
        """A client with its own node and a background executor thread.

        context=None: a private rclpy context is created (``rclpy.init(context=...)``) and shut
        down by ``close()``; a given context must already be initialised and is left running.
        """
        import os

        import rclpy
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.node import Node

        own_context = context is None
        if own_context:
            context = rclpy.Context()
            rclpy.init(context=context)
        try:
            name = node_name or f"memory_client_{os.getpid()}_{id(context) % 100000}"
            # a pure client: no parameter services, so each executor round has less to wait on
            node = Node(name, context=context, start_parameter_services=False)
            executor = SingleThreadedExecutor(context=context)
            executor.add_node(node)
        except Exception:
            if own_context:
                context.try_shutdown()
            raise
        thread = threading.Thread(target=_spin, args=(executor,), name=f"{name}_executor", daemon=True)
        thread.start()
        client = cls(node, memory_node, timeout=timeout)
        client._owned = (context if own_context else None, executor, thread)
        return client

    def close(self) -> None:
        """Destroy the service clients; a standalone client also stops its executor thread,
        destroys its node and shuts its private context down. Idempotent."""
        owned, self._owned = self._owned, None
        if owned is not None:
            context, executor, thread = owned
            executor.shutdown(timeout_sec=5.0)
            thread.join(timeout=5.0)
            self.node.destroy_node()
            if context is not None:
                context.try_shutdown()
        elif self._clients:
            for c in self._clients:
                self.node.destroy_client(c)
        self._clients = ()

    def __enter__(self) -> "MemoryClient":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # --- plumbing -----------------------------------------------------------------------------
    def wait_for_service(self, timeout: float | None = None) -> bool:
        """True once every service of the memory node is available (False after `timeout` s)."""
        deadline = time.monotonic() + (self.timeout if timeout is None else float(timeout))
        for c in self._clients:
            if not c.wait_for_service(timeout_sec=max(0.0, deadline - time.monotonic())):
                return False
        return True

    def _call(self, client, request, timeout: float | None):
        if self.node.executor is None:
            raise RuntimeError(f"MemoryClient: node {self.node.get_name()!r} is not spun by any executor; "
                               "spin it in a background thread or use MemoryClient.standalone()")
        timeout = self.timeout if timeout is None else float(timeout)
        done = threading.Event()
        future = client.call_async(request)
        future.add_done_callback(_waker(done))
        if not done.wait(timeout):
            client.remove_pending_request(future)
            future.cancel()
            raise TimeoutError(f"{client.srv_name}: no answer within {timeout:g} s "
                               "(is memory_node running and this node spun by an executor?)")
        response = future.result()
        if response is None:
            raise TimeoutError(f"{client.srv_name}: the call was cancelled")
        if getattr(response, "success", True) is False:
            raise MemoryServiceError(client.srv_name, response.message)
        return response

    # --- the memory's operations --------------------------------------------------------------
    def store(self, transitions: Transitions, *, timeout: float | None = None) -> StoreReply:
        """Store N transitions (value_labels required, one per transition), atomically."""
        req = Store.Request()
        transitions_to_batch(transitions, req.batch)
        r = self._call(self._store, req, timeout)
        return StoreReply(seq_to_numpy(r.identity_ids, np.uint64), int(r.new_identities), int(r.stored),
                          int(r.wal_sequence))

    def sample(self, k: int, source: str = "rtm", seed: int | None = None, *,
               num_batches: int = 1, timeout: float | None = None) -> tuple[Transitions, np.ndarray, np.ndarray]:
        """k distinct entries, uniformly, from RTM (default) or TM (the COMPER-M ablation).

        Returns (transitions, identity_ids uint64 [n], counts uint32 [n]) with n = k * num_batches
        (num_batches independent draws of k, one after the other); transitions.value_labels are QT
        predictions (RTM) or newest labels (TM). seed >= 0: a reproducible draw."""
        if source not in SOURCES:
            raise ValueError(f"sample: source must be 'rtm' or 'tm', got {source!r}")
        req = Sample.Request(batch_size=int(k), source=SOURCES[source], seed=-1 if seed is None else int(seed),
                             num_batches=int(num_batches))
        r = self._call(self._sample, req, timeout)
        return (batch_to_transitions(r.batch, validate=False), seq_to_numpy(r.identity_ids, np.uint64),
                seq_to_numpy(r.counts, np.uint32))

    def reduce(self, max_sets: int = 0, *, timeout: float | None = None) -> ReduceReply:
        """One-call reduction on the memory node (prediction = each set's newest label);
        max_sets 0 = the node's reduce_batch."""
        r = self._call(self._reduce, Reduce.Request(max_sets=int(max_sets)), timeout)
        return ReduceReply(int(r.sets_reduced), int(r.rtm_size), float(r.duration_s), r.message)

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
        s = self._call(self._stats, GetStats.Request(), timeout).stats
        return {name: getattr(s, name) for name in _STATS_FIELDS}

    def snapshot(self, path: str = "", *, timeout: float | None = None) -> tuple[str, int]:
        """Save a verified snapshot: '' = the node's storage_dir (checkpoint + WAL rotation), a
        relative name = under the node's snapshot_root, an absolute path only inside it (paths are
        on the node's machine; anything else is refused). Returns (path written, wal_sequence)."""
        r = self._call(self._snapshot, Snapshot.Request(op=Snapshot.Request.OP_SAVE, path=str(path)), timeout)
        return r.path, int(r.wal_sequence)

    def restore(self, path: str = "", *, timeout: float | None = None) -> tuple[str, int]:
        """Replace the node's state by the snapshot at `path` ('' = storage_dir's snapshot, else
        confined to snapshot_root like :meth:`snapshot`); a corrupted or incompatible snapshot,
        a path outside snapshot_root or a node with snapshot_service other than save_restore
        raises MemoryServiceError and leaves the state untouched."""
        r = self._call(self._snapshot, Snapshot.Request(op=Snapshot.Request.OP_RESTORE, path=str(path)), timeout)
        return r.path, int(r.wal_sequence)


def _waker(event: threading.Event):
    def wake(_future) -> None:
        event.set()
        # runs in the executor thread: give the GIL up once so the woken caller runs now instead
        # of after the executor's next round of Python bookkeeping (up to the switch interval)
        time.sleep(0)
    return wake


def _spin(executor) -> None:
    from rclpy.executors import ExternalShutdownException
    try:
        executor.spin()
    except (ExternalShutdownException, KeyboardInterrupt):
        pass

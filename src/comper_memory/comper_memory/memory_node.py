"""memory_node: the compact memory as a ROS 2 node (thin: translation between messages and the core).

Size: one translation per service (seven), each with its refusal paths, plus the snapshot path
confinement and the stats timer; the memory itself is comper_memory.core.

    ros2 run comper_memory memory_node
    ros2 run comper_memory memory_node --ros-args -p storage_dir:=memory_store -p delta:=1e-4
    ros2 run comper_memory memory_node --ros-args --params-file src/comper_memory/config/memory.yaml

Services (private, relative to the node, e.g. ``/memory_node/store``):

=================  ===========================  ============================================
``~/store``        comper_msgs/srv/Store        store a TransitionBatch with value labels
``~/sample``       comper_msgs/srv/Sample       k distinct entries from RTM (default) or TM
``~/reduce``       comper_msgs/srv/Reduce       one-call reduction, newest label = prediction
``~/reduce_begin`` comper_msgs/srv/ReduceBegin  phase 1 of a QT-driven reduction (lease)
``~/reduce_commit`` comper_msgs/srv/ReduceCommit phase 2: upsert RTM with QT's predictions
``~/get_stats``    comper_msgs/srv/GetStats     the current MemoryStats
``~/snapshot``     comper_msgs/srv/Snapshot     save / restore a verified snapshot
=================  ===========================  ============================================

Topic ``~/stats`` (comper_msgs/msg/MemoryStats), every ``stats_period_s``, best effort, keep last 1.
Parameters: every field of :class:`comper_memory.core.MemoryConfig` (read-only, declared with
``declare_config``) plus the node-level ``key_size``, ``stats_period_s``, ``sample_seed``,
``faiss_threads``, ``blas_threads``, ``executor_threads`` and the ``snapshot_*`` ones.

``~/snapshot`` paths are confined to ``snapshot_root`` (default ``<storage_dir>/snapshots``): a
relative path is taken under it, an absolute one must resolve inside it, links and ``..`` cannot
leave it, and the live storage can never be a target. Names follow
:mod:`comper_memory.snapshot_rules`, and named saves stay within its quota (``snapshot_max_count``,
``snapshot_max_bytes``, ``snapshot_min_free_bytes``). ROS 2 services carry no caller identity, so by
default peers may save but not restore (``snapshot_service`` save): a restore is done at start-up
(``snapshot_restore``) or by the process that embeds the node (:meth:`MemoryNode.restore_snapshot`);
deployments where only some peers may call use SROS2 enclaves (docs/security.md).

A refused request answers ``success=false`` with the reason in ``message`` and changes nothing
(the core validates a whole request before it touches any state); the node keeps serving.
Several learners may call at once: the services are in one reentrant callback group, so a
multi-threaded executor (``executor_threads`` >= 2, or an embedding process's) may run them
concurrently; the core serialises them with its own lock. ``main()`` uses a single-threaded
executor by default (``executor_threads`` 1): with one core lock it serves the same requests in
the same order at a third of rclpy's multi-threaded CPU cost per call; the request queue
(``SERVICE_QOS``, depth 1000) holds the other learners' calls meanwhile, and a store larger than
``store_chunk`` is applied in chunks with the other calls served in between.
All the memory logic lives in :mod:`comper_memory.core`.
"""
from __future__ import annotations

import collections
import contextlib
import os
import sys
import threading
import time
from dataclasses import dataclass

import numpy as np
import rclpy
from rclpy.callback_groups import ReentrantCallbackGroup
from rclpy.executors import MultiThreadedExecutor, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from comper_msgs.msg import MemoryStats
from comper_msgs.srv import GetStats, Reduce, ReduceBegin, ReduceCommit, Sample, Snapshot, Store
from comper_msgs_py.arrays import TransitionError
from comper_msgs_py.blas import set_numpy_blas_threads
from comper_msgs_py.convert import batch_to_transitions, numpy_to_seq, seq_to_numpy, transitions_to_batch
from comper_msgs_py.params import ConfigError, param
from comper_msgs_py.ros_main import serve_node
from comper_msgs_py.qos import SERVICE_QOS
from comper_msgs_py.ros_params import declare_config

from .core import CompactMemory, MemoryConfig, MemoryInputError, RateLimited, SnapshotError
from .snapshot_rules import NAME_MAX, NAME_RULE, SnapshotQuota, check_name, size_bound, usage

__all__ = ["MemoryNode", "MemoryNodeConfig", "main", "STATS_QOS", "SERVICE_QOS", "SOURCES", "stats_to_msg"]

# A periodic gauge: only the newest value matters (architecture.md, QoS table).
STATS_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1,
                       reliability=ReliabilityPolicy.BEST_EFFORT, durability=DurabilityPolicy.VOLATILE)

# Services: the suite's one service profile (comper_msgs_py.qos.SERVICE_QOS, the clients use it too):
# reliable, keep-last 1000, so neither a burst of requests nor of answers to other clients drops one.

SOURCES = {Sample.Request.SOURCE_RTM: "rtm", Sample.Request.SOURCE_TM: "tm"}

# Refusals: bad input, answered with success=false and the core's message (nothing changed).
_REFUSED = (MemoryInputError, TransitionError, SnapshotError, ConfigError)


def stats_to_msg(stats: dict, msg: MemoryStats | None = None) -> MemoryStats:
    """CompactMemory.stats() -> comper_msgs/MemoryStats (header left to the caller)."""
    msg = msg if msg is not None else MemoryStats()
    for name, kind in _STATS_TYPES.items():
        setattr(msg, name, float(stats[name]) if kind == "double" else int(stats[name]))
    return msg


#: every MemoryStats field but the header, with its type (the message is the one list of them)
_STATS_TYPES = {k: v for k, v in MemoryStats.get_fields_and_field_types().items() if k != "header"}


class _Refused(Exception):
    """A request the node itself refuses before it reaches the core."""


def _state_mark(memory: CompactMemory) -> tuple:
    """What any state-changing call changes (stores, reductions, leases, restores, the log position)."""
    s = memory.stats()
    return tuple(s[k] for k in ("identities", "tm_sets", "rtm_size", "transitions_stored", "reductions",
                                "sets_reduced", "evictions", "leases", "wal_sequence"))


class _Yield:
    """Awaitable that suspends a service coroutine once: rclpy's Task leaves it pending and its
    executor runs it again in its next round, after the entities that are ready by then."""

    def __await__(self):
        yield


async def _next_turn(executor) -> None:
    """Give the executor one round (other clients' calls) before the caller goes on. The wake
    makes that round's wait return at once instead of blocking until some other event."""
    if executor is not None:
        executor.wake()
    await _Yield()


@dataclass(frozen=True)
class MemoryNodeConfig:
    """memory_node's own parameters (the memory's are MemoryConfig, comper_memory.core)."""

    key_size: int = param(0, "length of the transition key [s, a, r, s'] (2*obs + action + 1); 0 = learnt from the "
                             "first store", minimum=0, maximum=2**31 - 1)
    stats_period_s: float = param(1.0, "period of the ~/stats topic in seconds (0 = not published)", minimum=0.0,
                                  maximum=3600.0)
    sample_seed: int = param(-1, "seed of the node's own sampling generator (used when a Sample request has "
                                 "seed < 0); -1 = from OS entropy", minimum=-1)
    faiss_threads: int = param(
        1, "OpenMP threads faiss may use in this process (0 = faiss's default, all cores). 1 is fastest for store "
        "batches of tens to thousands: several threads per small search cost more than they save",
        minimum=0, maximum=1024)
    blas_threads: int = param(
        1, "threads of numpy's OpenBLAS in this process (0 = the library's default, all cores); 1 keeps a store's "
        "key projection from competing with the other threads of a 2-core machine (docs/memory-service.md, "
        "Decisions). Process-wide, also when embedded", minimum=0, maximum=1024)
    store_chunk: int = param(
        1024, "transitions a ~/store call applies per turn of the executor: a larger batch is validated whole "
        "(a refused one stores nothing), then applied in chunks of this many, one WAL record each, and the "
        "node serves other clients' calls between chunks. 0 = every store in one turn (atomic, one WAL "
        "record; other clients wait for it) (docs/studies/memory-service-hardening.md)", minimum=0,
        maximum=2**31 - 1)
    executor_threads: int = param(
        1, "executor main() spins this node with: 1 = SingleThreadedExecutor (default: requests served one at a "
        "time, which the core's single lock does anyway, for less CPU per call than rclpy's "
        "MultiThreadedExecutor), >= 2 = MultiThreadedExecutor with that many threads (requests taken from DDS at "
        "once). Ignored when the node is embedded in another process", minimum=1, maximum=64)
    snapshot_service: str = param(
        "save", "what ~/snapshot lets peers do: save (default: OP_SAVE only; OP_RESTORE, which replaces the whole "
        "state, is refused: restore at start-up with snapshot_restore), save_restore (any peer on the ROS domain "
        "may also restore) or disabled (both refused). ROS 2 services carry no caller identity: use SROS2 "
        "security enclaves where only some peers may call (docs/security.md)",
        choices=("save", "save_restore", "disabled"))
    snapshot_restore: str = param(
        "", "a named snapshot (a name or path under snapshot_root, as in a ~/snapshot request) loaded at start-up, "
        "after storage_dir is recovered, replacing that state (with storage_dir it is then checkpointed there); "
        "'' = none. A missing or bad snapshot stops start-up. A ~/snapshot restore of this same snapshot while "
        "nothing has changed since is answered without loading it again, whatever snapshot_service says")
    snapshot_max_count: int = param(
        64, "most named snapshots under snapshot_root (directories holding a snapshot, up to 4 levels down): a save "
        "under a new name beyond it is refused (replacing an existing one is not). 0 = no limit",
        minimum=0, maximum=2**31 - 1)
    snapshot_max_bytes: int = param(
        32 * 2**30, "most bytes all named snapshots under snapshot_root may take: a save that could take them "
        "beyond it (its size bounded from the memory's arrays before anything is written) is refused. "
        "0 = no limit", minimum=0, maximum=2**62)
    snapshot_min_free_bytes: int = param(
        2**30, "free bytes a named snapshot save must leave on snapshot_root's file system (the storage_dir's "
        "write-ahead log may share it): a save that could leave less is refused. 0 = no check",
        minimum=0, maximum=2**62)
    snapshot_root: str = param(
        "", "the only directory ~/snapshot may write or read named snapshots in (a relative request path is taken "
        "under it; an absolute one must lie inside it after resolving links). '' = <storage_dir>/snapshots, or no "
        "named snapshots at all without storage_dir. It must not be the storage directory or contain it. An "
        "existing target is replaced only if it is a snapshot (manifest.json + state.npz and nothing else)")


class MemoryNode(Node):
    """The compact-memory node. ``node_kwargs`` go to rclpy's Node (context, parameter_overrides,
    namespace, ...), so an agent can embed it in its own process (``bringup``).

    Raises at construction when a parameter is bad or the storage directory cannot be opened
    (e.g. a corrupted snapshot in ``storage_dir``).
    """

    def __init__(self, node_name: str = "memory_node", **node_kwargs):
        super().__init__(node_name, **node_kwargs)
        try:
            self.config: MemoryConfig = declare_config(self, MemoryConfig).validate()
            self.p = p = declare_config(self, MemoryNodeConfig)
            self.key_size, self.stats_period_s, self.sample_seed = p.key_size, p.stats_period_s, p.sample_seed
            self.faiss_threads, self.blas_threads = p.faiss_threads, p.blas_threads
            self.executor_threads, self.snapshot_service, self.snapshot_root = (
                p.executor_threads, p.snapshot_service, p.snapshot_root)
            self.store_chunk = p.store_chunk
            if self.faiss_threads > 0:
                import faiss
                faiss.omp_set_num_threads(self.faiss_threads)
            if self.blas_threads > 0 and set_numpy_blas_threads(self.blas_threads) is None:
                self.get_logger().warning("blas_threads: numpy's BLAS is not OpenBLAS; its threads are unchanged")
            self._snapshot_root = self._check_snapshot_root()
            self.snapshot_quota = SnapshotQuota(p.snapshot_max_count, p.snapshot_max_bytes,
                                                p.snapshot_min_free_bytes)
            self.memory = CompactMemory(self.config, self.key_size or None,
                                        log=lambda text: self.get_logger().warning(text))
            # (path, state fingerprint) of the snapshot_restore loaded at start-up
            self._restored_at_start: tuple[str, tuple] | None = None
            if p.snapshot_restore:
                self._restore_at_start(p.snapshot_restore)
        except Exception:
            if getattr(self, "memory", None) is not None:
                self.memory.close()
            super().destroy_node()
            raise
        self._rng = np.random.default_rng(None if self.sample_seed < 0 else self.sample_seed)
        self._closed = False
        self._close_lock = threading.Lock()
        self._warn_lock = threading.Lock()
        self._warn_last = -1e9
        self._warn_suppressed = 0
        # snapshot answers by request id (a re-sent save or restore is answered, not carried out again);
        # the lock also keeps a re-send from running beside its first call under a multi-threaded executor
        self._snapshot_lock = threading.Lock()
        self._snapshot_answers: collections.OrderedDict[int, tuple[bool, str, int, str]] = collections.OrderedDict()
        self._group = ReentrantCallbackGroup()
        g = self._group
        self._stats_pub = self.create_publisher(MemoryStats, "~/stats", STATS_QOS, callback_group=g)
        for srv_type, name, cb in ((Store, "~/store", self._on_store), (Sample, "~/sample", self._on_sample),
                                   (Reduce, "~/reduce", self._on_reduce),
                                   (ReduceBegin, "~/reduce_begin", self._on_reduce_begin),
                                   (ReduceCommit, "~/reduce_commit", self._on_reduce_commit),
                                   (GetStats, "~/get_stats", self._on_get_stats),
                                   (Snapshot, "~/snapshot", self._on_snapshot)):
            self.create_service(srv_type, name, cb, qos_profile=SERVICE_QOS, callback_group=g)
        self._timer = (self.create_timer(self.stats_period_s, self.publish_stats, callback_group=g)
                       if self.stats_period_s > 0 else None)
        c, s = self.config, self.memory.stats()
        storage = (f"storage {os.path.abspath(c.storage_dir)} (durability {c.durability}, snapshot "
                   f"every {c.snapshot_every} ops; recovered {s['identities']} identities, "
                   f"wal_sequence {s['wal_sequence']})" if c.storage_dir else "in memory only (no storage_dir)")
        self.get_logger().info(
            f"serving: delta {c.delta:g}, key_size {self.memory.key_size or 'from first store'}, "
            f"rtm_capacity {c.rtm_capacity}, tm_capacity {c.tm_capacity}, history_length "
            f"{c.history_length}, reduce_batch {c.reduce_batch}, max_store_batch {c.max_store_batch}, "
            f"max_sample_batch {c.max_sample_batch}, lease_timeout_s {c.lease_timeout_s:g}, "
            f"stats every {self.stats_period_s:g} s, executor_threads {self.executor_threads}, faiss_threads {self.faiss_threads or 'default'}, blas_threads {self.blas_threads or 'default'}; {storage}")

    def make_executor(self, context=None):
        """The executor of ``executor_threads`` (also used when another process embeds this node)."""
        if self.executor_threads > 1:
            return MultiThreadedExecutor(num_threads=self.executor_threads, context=context)
        return SingleThreadedExecutor(context=context)

    # --- helpers ------------------------------------------------------------------------------
    def _refuse(self, response, what: str, exc: Exception):
        if isinstance(exc, RateLimited):   # normal flow control: the client retries; not logged
            response.message = str(exc)
            response.rate_limited = True
            response.success = False
            return response
        if isinstance(exc, (_Refused,) + _REFUSED):
            response.message = str(exc)
            self._warn(f"{what} refused: {exc}", error=False)
        else:  # a bug or an I/O failure: report it, keep serving
            response.message = f"internal error: {type(exc).__name__}: {exc}"
            self._warn(f"{what} failed: {type(exc).__name__}: {exc}", error=True)
        response.success = False
        return response

    def _warn(self, text: str, *, error: bool) -> None:
        """At most one line per second, however many learners send bad requests; the next line
        says how many were not logged."""
        now = time.monotonic()
        with self._warn_lock:
            if now - self._warn_last < 1.0:
                self._warn_suppressed += 1
                return
            self._warn_last, skipped, self._warn_suppressed = now, self._warn_suppressed, 0
        if skipped:
            text += f" ({skipped} more refused or failed requests not logged)"
        (self.get_logger().error if error else self.get_logger().warning)(text)

    @contextlib.contextmanager
    def _open(self):
        """Held around every state-changing core call: after close() (final WAL flush) nothing
        more is acknowledged. The core serialises these calls anyway, so this costs no concurrency."""
        with self._close_lock:
            if self._closed:
                raise _Refused("the memory node is shutting down")
            yield

    def _stats(self) -> dict:
        s = {**self.memory.stats(), **self.memory.rate_stats()}
        if not self.config.storage_dir:
            s["wal_sequence"] = 0  # MemoryStats: 0 when not persistent
        return s

    def publish_stats(self) -> None:
        if self._closed:
            return
        msg = stats_to_msg(self._stats())
        msg.header.stamp = self.get_clock().now().to_msg()
        self._stats_pub.publish(msg)

    # --- services -----------------------------------------------------------------------------
    async def _on_store(self, request: Store.Request, response: Store.Response):
        """A coroutine: rclpy's executors resume it after serving what else is ready, so a store of
        more than ``store_chunk`` transitions lets other calls in between its chunks."""
        op = None
        try:
            n = len(request.batch.rewards)
            if n == 0:
                raise _Refused("store: empty batch (0 transitions)")
            if n > self.config.max_store_batch:
                raise _Refused(f"store: batch of {n} exceeds max_store_batch ({self.config.max_store_batch})")
            t = batch_to_transitions(request.batch)
            with self._open():
                # validates all and applies chunk 1; a re-send of a store in progress or remembered gets that one
                op = self.memory.begin_store(t, self.store_chunk, request_id=int(request.request_id),
                                             relabel=bool(request.relabel))
            while not op.done:
                await _next_turn(self.executor)
                with self._open():
                    op.step()
            result = op.result()
        except Exception as exc:
            self._refuse(response, "store", exc)
            if op is not None and 0 < op.applied < op.n:   # not bad input: a shutdown or an I/O failure
                response.message += (f" ({op.applied} of the batch's {op.n} transitions, its first chunks, "
                                     "were stored before this)")
            return response
        response.success = True
        response.stored = n
        response.new_identities = int(result.new_identities)
        response.identity_ids = numpy_to_seq(result.identity_ids, np.uint64)
        response.wal_sequence = int(result.wal_sequence) if self.config.storage_dir else 0
        response.repeated = bool(op.repeated)
        return response

    def _on_sample(self, request: Sample.Request, response: Sample.Response):
        try:
            source = SOURCES.get(request.source)
            if source is None:
                raise _Refused(f"sample: unknown source {request.source} (SOURCE_RTM=0, SOURCE_TM=1)")
            nb = int(request.num_batches)
            if request.seed >= 0:
                result = self.memory.sample(request.batch_size, source, seed=int(request.seed), num_batches=nb)
            else:  # the core holds its lock while it draws, so sharing one generator is safe
                result = self.memory.sample(request.batch_size, source, rng=self._rng, num_batches=nb)
        except Exception as exc:
            return self._refuse(response, "sample", exc)
        transitions_to_batch(result.transitions, response.batch)
        response.identity_ids = numpy_to_seq(result.identity_ids, np.uint64)
        response.counts = numpy_to_seq(result.counts, np.uint32)
        response.success = True
        return response

    def _on_reduce(self, request: Reduce.Request, response: Reduce.Response):
        t0 = time.perf_counter()
        try:
            with self._open():
                result = self.memory.reduce(max_sets=request.max_sets or None)
        except Exception as exc:
            return self._refuse(response, "reduce", exc)
        response.success = True
        response.sets_reduced = int(result.upserted)
        response.rtm_size = int(self.memory.rtm_size)
        response.qt_version = 0
        response.qt_loss = 0.0
        response.duration_s = time.perf_counter() - t0
        if result.skipped:
            response.message = f"{result.skipped} leased identities were evicted meanwhile"
        return response

    def _on_reduce_begin(self, request: ReduceBegin.Request, response: ReduceBegin.Response):
        try:
            with self._open():
                lease = self.memory.begin_reduce(request.max_sets or None)
        except Exception as exc:
            return self._refuse(response, "reduce_begin", exc)
        sets = response.sets
        sets.reduction_id = int(lease.reduction_id)
        sets.identity_ids = numpy_to_seq(lease.identity_ids, np.uint64)
        transitions_to_batch(lease.representatives, sets.representatives)
        sets.label_history = numpy_to_seq(lease.label_history, np.float32)
        sets.history_lengths = numpy_to_seq(lease.history_lengths, np.uint32)
        sets.counts = numpy_to_seq(lease.counts, np.uint32)
        response.success = True
        return response

    def _on_reduce_commit(self, request: ReduceCommit.Request, response: ReduceCommit.Response):
        try:
            ids = seq_to_numpy(request.identity_ids, np.uint64)
            if ids.size and int(ids.max()) >= 2**63:
                raise _Refused("reduce_commit: identity_ids out of range")
            with self._open():
                result = self.memory.commit_reduce(int(request.reduction_id), ids.astype(np.int64),
                                                   seq_to_numpy(request.predictions, np.float32))
        except Exception as exc:
            return self._refuse(response, "reduce_commit", exc)
        response.success = True
        response.committed = int(result.upserted)
        response.rtm_size = int(self.memory.rtm_size)
        if result.skipped:
            response.message = f"{result.skipped} leased identities were evicted meanwhile"
        return response

    def _on_get_stats(self, request: GetStats.Request, response: GetStats.Response):
        stats_to_msg(self._stats(), response.stats)
        response.stats.header.stamp = self.get_clock().now().to_msg()
        return response

    def _check_snapshot_root(self) -> str | None:
        """The resolved snapshot_root (None: no named snapshots); refuses a root that is or holds
        the live storage (a save there could replace the WAL and the live snapshot)."""
        storage = os.path.realpath(self.config.storage_dir) if self.config.storage_dir else None
        root = self.snapshot_root or (os.path.join(storage, "snapshots") if storage else "")
        if not root:
            return None
        root = os.path.realpath(root)
        if storage is not None:
            if root == storage or os.path.commonpath([root, storage]) == root:
                raise ConfigError(f"snapshot_root {root!r} is or contains storage_dir {storage!r}: "
                                  "a snapshot there could replace the live log; choose another directory")
            live = os.path.join(storage, "snapshot")
            if os.path.commonpath([root, live]) == live:
                raise ConfigError(f"snapshot_root {root!r} lies inside the live snapshot {live!r}")
        return root

    def _default_snapshot_path(self) -> str:
        if not self.config.storage_dir:
            raise _Refused("snapshot: empty path and the node has no storage_dir; give a path "
                           "under snapshot_root")
        return os.path.join(os.path.realpath(self.config.storage_dir), "snapshot")

    def _named_snapshot_path(self, path: str) -> str:
        """A request path confined to snapshot_root (links resolved; '..' cannot leave it)."""
        root = self._snapshot_root
        if root is None:
            raise _Refused(f"snapshot: path {path!r} refused: this node has no snapshot_root (set "
                           "-p snapshot_root:=DIR or storage_dir); only the empty path (the node's own "
                           "storage) is served")
        if "\0" in path:
            raise _Refused("snapshot: path holds a NUL character")
        if len(path) > len(root) + 1 + NAME_MAX:     # before any file-system call (a name too long for it)
            raise _Refused(f"snapshot: a path of {len(path)} characters is refused ({NAME_RULE})")
        full = os.path.normpath(path if os.path.isabs(path) else os.path.join(root, path))
        if os.path.islink(full):
            raise _Refused(f"snapshot: path {path!r} is a symbolic link; refused")
        full = os.path.join(os.path.realpath(os.path.dirname(full)), os.path.basename(full))
        if full == root or os.path.commonpath([full, root]) != root:
            raise _Refused(f"snapshot: path {path!r} is outside snapshot_root {root!r}; give a name "
                           "(relative paths are taken under snapshot_root) or an absolute path inside it")
        check_name(os.path.relpath(full, root))
        return full

    def _restore_at_start(self, name: str) -> None:
        """snapshot_restore: load the named snapshot before serving; ConfigError (cannot start) if it fails."""
        try:
            path = self._named_snapshot_path(name)
            if not os.path.isdir(path):
                raise _Refused(f"{path!r} is not a snapshot directory")
            self.memory.load_snapshot(path)
        except (_Refused, SnapshotError, MemoryInputError) as exc:
            raise ConfigError(f"snapshot_restore {name!r}: {exc}; start without snapshot_restore to keep the "
                              "state the node recovers by itself") from None
        self._restored_at_start = (path, _state_mark(self.memory))
        s = self.memory.stats()
        self.get_logger().info(f"restored at start-up from {path} (snapshot_restore): {s['identities']} "
                               f"identities, TM sets {s['tm_sets']}, RTM {s['rtm_size']}")

    def _restore_refused(self, request: Snapshot.Request) -> tuple[str, str]:
        """A peer's restore while snapshot_service is not save_restore: refused, unless it asks for the
        snapshot_restore loaded at start-up and nothing has changed since (then it changes nothing)."""
        path = None
        with contextlib.suppress(_Refused, SnapshotError):      # a name outside the rules is not echoed
            path = self._named_snapshot_path(request.path) if request.path else None
        if self._restored_at_start is not None and path is not None:
            start_path, mark = self._restored_at_start
            if path == start_path and _state_mark(self.memory) == mark:
                return start_path, "already restored at start-up (nothing changed since):"
        what = repr(request.path) if path else "a named snapshot" if request.path else "the storage snapshot"
        hint = (f"restart the node with -p snapshot_restore:={request.path if path else 'NAME'} to restore it at "
                "start-up, or " if request.path else "")
        raise _Refused(f"snapshot: restore is off on this node (snapshot_service {self.snapshot_service}): peers "
                       f"may not replace the memory's state. To restore {what}, {hint}allow restores through the "
                       "service with -p snapshot_service:=save_restore (any peer on the ROS domain may then "
                       "restore; docs/security.md)")

    def _snapshot(self, request: Snapshot.Request, *, peer: bool = True) -> tuple[str, str]:
        """peer=False: a call of the process that embeds this node (restore_snapshot), which
        snapshot_service does not gate."""
        if peer and self.snapshot_service == "disabled":
            raise _Refused("snapshot: this node's snapshot service is off (snapshot_service disabled)")
        if request.op == Snapshot.Request.OP_SAVE:
            if request.path:
                path, root = self._named_snapshot_path(request.path), self._snapshot_root
                # within the quota, checked against a bound of its size before anything is written (the
                # snapshot it replaces does not count)
                count, used = usage(root, exclude=path)
                self.memory.save_snapshot(path, admit=lambda arrays, meta: self.snapshot_quota.check(
                    root, path, count, used, size_bound(arrays, meta)))
            else:  # snapshot into storage_dir and rotate the WAL
                path = self._default_snapshot_path()
                self.memory.checkpoint()
            return path, "saved"
        if request.op == Snapshot.Request.OP_RESTORE:
            if peer and self.snapshot_service != "save_restore":
                return self._restore_refused(request)
            path = self._named_snapshot_path(request.path) if request.path else self._default_snapshot_path()
            if not os.path.isdir(path):
                raise _Refused(f"snapshot: {path!r} is not a snapshot directory")
            self.memory.load_snapshot(path)
            return path, "restored"
        raise _Refused(f"snapshot: unknown op {request.op} (OP_SAVE=0, OP_RESTORE=1)")

    def restore_snapshot(self, path: str) -> tuple[str, int]:
        """OP_RESTORE for the process that embeds this node (a learner resuming its run), with the checks of
        a ~/snapshot restore (path confined to snapshot_root, the snapshot verified whole) whatever
        snapshot_service says: that parameter gates peers. (path, wal_sequence); SnapshotError with the
        reason when refused (nothing changed)."""
        request = Snapshot.Request(op=Snapshot.Request.OP_RESTORE, path=path)
        with self._snapshot_lock:
            try:
                with self._open():
                    path, what = self._snapshot(request, peer=False)
            except (_Refused,) + _REFUSED as exc:
                raise SnapshotError(str(exc)) from None
        seq = int(self._stats()["wal_sequence"])
        self.get_logger().info(f"snapshot {what} (in process): {path} (wal_sequence {seq})")
        return path, seq

    #: how many snapshot answers the node remembers by request id (Snapshot.srv)
    SNAPSHOT_ANSWERS = 64

    def _on_snapshot(self, request: Snapshot.Request, response: Snapshot.Response):
        """A request id seen before gets the first call's answer, a refusal included: a client re-sends a long
        save every resend_s, and those copies queue behind it; each was carried out again after a failed save."""
        rid = int(request.request_id)
        with self._snapshot_lock:
            remembered = self._snapshot_answers.get(rid) if rid else None
            if remembered is None:
                try:
                    with self._open():
                        path, what = self._snapshot(request)
                except Exception as exc:
                    self._refuse(response, "snapshot", exc)
                    remembered = (False, "", 0, response.message)
                else:
                    remembered = (True, path, int(self._stats()["wal_sequence"]), f"{what} {path}")
                    self.get_logger().info(f"snapshot {what}: {path} (wal_sequence {remembered[2]})")
                if rid:
                    self._snapshot_answers[rid] = remembered
                    while len(self._snapshot_answers) > self.SNAPSHOT_ANSWERS:
                        self._snapshot_answers.popitem(last=False)
            else:
                response.repeated = True
        response.success, response.path, response.wal_sequence, response.message = remembered
        return response

    # --- shutdown -----------------------------------------------------------------------------
    def close(self) -> None:
        """Flush and close the write-ahead log (idempotent); the node stops answering stores."""
        with self._close_lock:
            if self._closed:
                return
            self._closed = True
            memory = getattr(self, "memory", None)
            if memory is not None:
                memory.close()

    def destroy_node(self):
        if hasattr(self, "memory"):
            self.close()
        return super().destroy_node()


def main(args=None) -> int:
    """Entry point of ``ros2 run comper_memory memory_node``: 0 on Ctrl-C / SIGTERM, 1 when it
    cannot start (bad parameter, unreadable storage_dir)."""
    def close(node: MemoryNode) -> None:
        node.close()  # final flush of the WAL
        # after Ctrl-C the context is already shut down: log without the node (no rosout)
        rclpy.logging.get_logger("memory_node.main").info(
            "stopped" + (" (write-ahead log flushed and closed)" if node.config.storage_dir else ""))

    return serve_node(MemoryNode, "memory_node", args, on_close=close)


if __name__ == "__main__":
    sys.exit(main())

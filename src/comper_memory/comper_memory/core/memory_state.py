"""MemoryState: what a compact memory holds, and the state in and out of its snapshots and WAL.

:class:`MemoryState` is the memory's data, one object: the schema, the slot table, TM and RTM with the remover and
the reduction, the similarity index, the key normaliser, the store registry and the counters (``COUNTERS``). Its
methods apply what was validated and logged (:meth:`~MemoryState.apply_store`, :meth:`~MemoryState.apply_commit`),
say what a snapshot holds (:meth:`~MemoryState.arrays`, :meth:`~MemoryState.restore`) and replay a WAL record
(:meth:`~MemoryState.replay`). :class:`~.memory.CompactMemory` holds one, with the lock, the log and the rate
limiter, and calls it with its lock held; :class:`~.durability.Durability` writes and reads the files. Nothing here
reaches back into the memory: what a replayed chunk needs of it comes as an explicit
:class:`~.chunked_store.StoreTarget`.
"""
from __future__ import annotations

import dataclasses

import numpy as np

from comper_msgs_py.arrays import Transitions

from . import storage as st
from .chunked_store import StoreRegistry, StoreTarget, check_registry
from .config import MemoryConfig
from .durability import COUNTERS, arrays_to_t, check_counters
from .frames import check_snapshot_obs, frame_layout, layout_meta, written_layout
from .index import make_index
from .key_norm import KeyNormaliser, resolve_store
from .reduction import Reduction
from .results import CommitResult, MemoryInputError, StoreResult
from .similarity import ResolveResult, SimilarityIndex
from .slots import SlotTable
from .tables import ReducedTable, Remover, TransitionTable
from .validation import index_key_size, schema_of, validate_store

__all__ = ["MemoryState"]


class MemoryState:
    """The memory's data (module text). ``index_engine``: None = the config's choice; tests and benchmarks may
    force 'grid' or 'ivf' before the first store. ``expected_key_size``: the key size a snapshot must have."""

    def __init__(self, config: MemoryConfig, expected_key_size: int | None = None):
        self.config = config
        self.expected_key_size = expected_key_size
        self.index_engine: str | None = None
        # chunked stores in progress and re-sent stores' answers by request id (a restore keeps the ones in
        # progress: the registry lives as long as the memory, not as one state)
        self.stores = StoreRegistry(config.resend_window)
        self.reset()

    def reset(self) -> None:
        """Empty: no schema, no identities, counters at 0."""
        c = self.config
        self.schema: dict | None = None   # obs_shape, obs_dtype, action_shape, action_dtype, key_size
        self.index: SimilarityIndex | None = None
        self.key_norm = KeyNormaliser(c.key_normalisation, c.key_norm_growth, c.key_norm_min_std, c.delta_rule,
                                      c.delta, c.delta_quantile)
        self.slots = SlotTable(c.history_length, c.frame_scale, self.key_norm)
        self.a = self.slots.a   # the slot columns (one dict for the table's life; tests read it)
        self.tm = TransitionTable(self.slots)
        self.rtm = ReducedTable(self.slots)
        self.remover = Remover(self.slots, self.tm, self.rtm, c.rtm_capacity, c.tm_capacity, c.removal,
                               c.removal_seed)
        self.reduction = Reduction(self.slots, self.tm, self.rtm)
        for name in COUNTERS:
            setattr(self, name, 0)
        self.next_reduction_id = 1

    def init_schema(self, schema: dict) -> None:
        """The first store (or a snapshot) fixes the transitions' shapes, whether observations are kept as frames
        (``frame_store``, frames.py) and the index's key size; MemoryInputError (nothing set) if ``frame_axis``
        does not fit the observations."""
        c = self.config
        try:
            layout = frame_layout(c.frame_store, c.frame_axis, schema["obs_shape"], schema["obs_dtype"])
        except ValueError as e:
            raise MemoryInputError(f"store: {e}") from None
        schema = {**schema, "frames": layout_meta(layout)}
        self.schema = schema
        self.slots.set_schema(schema, layout)
        key = index_key_size(schema["obs_shape"], schema["action_shape"])
        self.index = make_index(self.config, key, self.slots, self.index_engine)

    # ------------------------------------------------------------------ operations, validated and logged
    def apply_store(self, t: Transitions, y: np.ndarray, res: ResolveResult, raw_keys: np.ndarray) -> StoreResult:
        """Apply a validated store whose similarity decisions are ``res`` (keys ``y`` in the index's space)."""
        n = len(t)
        self.key_norm.observe(raw_keys)
        cidx = np.flatnonzero(res.creates)
        n_new = len(cidx)
        new_ids = self.next_id + np.arange(n_new, dtype=np.int64)
        self.next_id += n_new
        new_slots = self.slots.create(new_ids, t, cidx)
        # target identity / slot for each transition
        tid = np.empty(n, dtype=np.int64)
        tslot = np.empty(n, dtype=np.int64)
        tid[cidx] = new_ids
        tslot[cidx] = new_slots
        ex = res.existing >= 0
        tid[ex] = res.existing[ex]
        tslot[ex] = self.slots.slots_of(res.existing[ex])
        bj = res.batch >= 0
        tid[bj] = tid[res.batch[bj]]   # creators come before their joiners
        tslot[bj] = tslot[res.batch[bj]]
        useg, first_seq = self.slots.record(tslot, t.value_labels, t.steps, self.transitions_stored)
        # TM: sets not in TM enter at the back, in order of their first transition of this batch
        enter = ~self.tm.contains(useg)
        if enter.any():
            fs = first_seq[enter]
            o = np.argsort(fs)
            self.tm.enter(useg[enter][o], fs[o])
        self.transitions_stored += n
        hits = n - n_new
        self.similarity_hits += hits
        if n_new:
            self.index.add(new_ids, y[cidx])
        evicted = self.remover.enforce(self.index, new_ids)
        self.evictions += evicted
        return StoreResult(tid, int(n_new), int(hits), int(evicted), self.wal_sequence)

    def apply_commit(self, rid, ids, preds, in_tm, tm_key, replay: bool = False) -> CommitResult:
        """Apply a checked reduction commit: upsert its identities into RTM."""
        n = self.reduction.apply(rid, ids, preds, in_tm, tm_key, replay)
        if self.key_norm.maybe_freeze(self._live_raw_keys):   # new mean/scale: every identity's key changes
            self.index = make_index(self.config, self.index.key_dim, self.slots, self.index_engine)
            self.index.reindex()
        self.reductions += 1
        self.sets_reduced += n
        return CommitResult(rid, n, len(ids) - n, self.wal_sequence)

    def _live_raw_keys(self, k: int) -> np.ndarray:
        """Raw keys of up to ``k`` live identities evenly spread over the ids (the delta rule's sample)."""
        slots = self.slots.slots_sorted
        pick = np.unique(np.linspace(0, len(slots) - 1, min(len(slots), k)).astype(np.int64))
        return self.slots.raw_keys_of_slots(slots[pick])

    # ------------------------------------------------------------------ snapshots and the WAL
    def arrays(self) -> tuple[dict[str, np.ndarray], dict]:
        """(arrays, meta) of a snapshot: live identities ordered by id, TM/RTM order, counters."""
        arrays = {}
        if self.schema is not None:
            arrays = self.slots.rows()
            self.tm.snapshot_into(arrays)
            self.rtm.snapshot_into(arrays)
            arrays.update(self.key_norm.arrays())
            arrays.update(self.stores.arrays())
        c, sch = self.config, self.schema
        meta = {"schema": None if sch is None else
                {**sch, "obs_shape": list(sch["obs_shape"]), "action_shape": list(sch["action_shape"])},
                "history_length": c.history_length, "delta": c.delta, "frame_scale": c.frame_scale,
                **_key_norm_meta(dataclasses.asdict(c)),
                "counters": {k: int(getattr(self, k)) for k in COUNTERS}}
        return arrays, meta

    def restore(self, arrays: dict[str, np.ndarray], meta: dict, target: StoreTarget) -> None:
        """Replace the state by a snapshot's; SnapshotError (state untouched) if it does not fit. ``target``: what
        the snapshot's stores cut short are completed against when their clients re-send them."""
        c = self.config
        if meta.get("history_length") != c.history_length or meta.get("delta") != c.delta or \
                meta.get("frame_scale") != c.frame_scale:
            raise st.SnapshotError("snapshot was written with a different delta, frame_scale or "
                                   "history_length than this memory's configuration")
        ours = _key_norm_meta(dataclasses.asdict(c))
        if _key_norm_meta(meta) != ours:
            raise st.SnapshotError(f"snapshot was written with key normalisation {_key_norm_meta(meta)}, this "
                                   f"memory is configured with {ours}")
        sch = meta.get("schema")
        if sch is not None and self.expected_key_size is not None and sch["key_size"] != self.expected_key_size:
            raise st.SnapshotError(f"snapshot key size {sch['key_size']} differs from {self.expected_key_size}")
        check_counters(arrays, meta)
        written = None
        if sch is not None and arrays:
            try:
                written = written_layout(sch)
                frame_layout(c.frame_store, c.frame_axis, sch["obs_shape"], sch["obs_dtype"])
            except ValueError as e:
                raise st.SnapshotError(f"snapshot does not fit this memory: {e}") from None
            bad = check_snapshot_obs(arrays, written)
            if bad:
                raise st.SnapshotError(f"snapshot {bad}")
        bad = check_registry(arrays)
        if bad:
            raise st.SnapshotError(f"snapshot {bad}")
        self.reset()
        for k, v in meta["counters"].items():
            setattr(self, k, int(v))
        self.stores.load(target, arrays)
        if sch is None:
            return
        self.init_schema({**sch, "obs_shape": tuple(sch["obs_shape"]), "action_shape": tuple(sch["action_shape"])})
        self.slots.load_rows(arrays, written)
        self.tm.restore(arrays["tm_order"])
        self.rtm.restore(arrays["rtm_order"])
        self.key_norm.load(arrays)
        self.index.reindex()

    def replay(self, seq: int, kind: int, arr: dict[str, np.ndarray], target: StoreTarget) -> None:
        """Apply one logged operation (recovery) as it was applied when it was logged."""
        if kind == st.WAL_STORE:
            clean, keys = validate_store(arrays_to_t(arr), self.config, self.schema, self.expected_key_size,
                                         replay=True)
            if self.schema is None:
                self.init_schema(schema_of(clean))
            y, res = resolve_store(self.index, self.key_norm, keys)
            self.wal_sequence = seq
            part = self.apply_store(clean, y, res, keys)
            if "request" in arr:   # a chunk of a store whose answer the memory remembers
                self.stores.replayed(target, arr["request"], part)
        elif kind == st.WAL_COMMIT:
            self.wal_sequence = seq
            self.next_reduction_id += 1
            self.apply_commit(-1, arr["ids"], arr["preds"], arr["in_tm"], arr["tm_key"], replay=True)
        else:
            raise st.SnapshotError(f"WAL record {seq}: unknown kind {kind}")


def _key_norm_meta(settings: dict) -> dict:
    """The key normaliser's settings a snapshot records and must match, from a config (as a dict) or a
    snapshot's meta (written before the option: none). With 'running' its growth and floor decide when
    the frozen map changes, so a WAL replayed on top of the snapshot must use the same ones."""
    rule = {} if settings.get("delta_rule", "fixed") == "fixed" else \
        {k: settings.get(k) for k in ("delta_rule", "delta_quantile", "key_norm_growth")}
    if settings.get("key_normalisation", "none") == "none":
        return {"key_normalisation": "none", **rule}
    return {**{k: settings.get(k) for k in ("key_normalisation", "key_norm_growth", "key_norm_min_std")}, **rule}

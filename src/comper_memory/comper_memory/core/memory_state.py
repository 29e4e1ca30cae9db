"""The memory's state in and out: snapshot arrays + metadata, restore, and WAL replay.

:class:`~.durability.Durability` writes and reads the files; these functions say what the state
of a :class:`~.memory.CompactMemory` is in them: the slot table's rows, TM and RTM order, the
schema, the configuration a snapshot must match and the counters (``COUNTERS``). Each takes the
memory and is called with its lock held (or during its construction, by recovery).
"""
from __future__ import annotations

import dataclasses
from typing import TYPE_CHECKING

import numpy as np

from . import storage as st
from .chunked_store import check_registry
from .durability import COUNTERS, arrays_to_t, check_counters
from .key_norm import resolve_store
from .validation import schema_of, validate_store

if TYPE_CHECKING:
    from .memory import CompactMemory

__all__ = ["state_arrays", "restore_state", "replay_record"]


def state_arrays(mem: CompactMemory) -> tuple[dict[str, np.ndarray], dict]:
    """(arrays, meta) of a snapshot: live identities ordered by id, TM/RTM order, counters."""
    arrays = {}
    if mem.schema is not None:
        arrays = mem.slots.rows()
        mem.tm.snapshot_into(arrays)
        mem.rtm.snapshot_into(arrays)
        arrays.update(mem.key_norm.arrays())
        arrays.update(mem.stores.arrays())
    c, sch = mem.config, mem.schema
    meta = {"schema": None if sch is None else
            {**sch, "obs_shape": list(sch["obs_shape"]), "action_shape": list(sch["action_shape"])},
            "history_length": c.history_length, "delta": c.delta, "frame_scale": c.frame_scale,
            **_key_norm_meta(dataclasses.asdict(c)),
            "counters": {k: int(getattr(mem, k)) for k in COUNTERS}}
    return arrays, meta


def restore_state(mem: CompactMemory, arrays: dict[str, np.ndarray], meta: dict) -> None:
    """Replace mem's state by a snapshot's; SnapshotError (state untouched) if it does not fit."""
    c = mem.config
    if meta.get("history_length") != c.history_length or meta.get("delta") != c.delta or \
            meta.get("frame_scale") != c.frame_scale:
        raise st.SnapshotError("snapshot was written with a different delta, frame_scale or "
                               "history_length than this memory's configuration")
    ours = _key_norm_meta(dataclasses.asdict(c))
    if _key_norm_meta(meta) != ours:
        raise st.SnapshotError(f"snapshot was written with key normalisation {_key_norm_meta(meta)}, this memory "
                               f"is configured with {ours}")
    sch = meta.get("schema")
    if sch is not None and mem.expected_key_size is not None and sch["key_size"] != mem.expected_key_size:
        raise st.SnapshotError(f"snapshot key size {sch['key_size']} differs from {mem.expected_key_size}")
    check_counters(arrays, meta)
    bad = check_registry(arrays)
    if bad:
        raise st.SnapshotError(f"snapshot {bad}")
    mem._reset_state()
    for k, v in meta["counters"].items():
        setattr(mem, k, int(v))
    mem.stores.load(mem, arrays)
    if sch is None:
        return
    mem._init_schema({**sch, "obs_shape": tuple(sch["obs_shape"]), "action_shape": tuple(sch["action_shape"])})
    mem.slots.load_rows(arrays)
    mem.tm.restore(arrays["tm_order"])
    mem.rtm.restore(arrays["rtm_order"])
    mem.key_norm.load(arrays)
    mem.index.reindex()


def replay_record(mem: CompactMemory, seq: int, kind: int, arr: dict[str, np.ndarray]) -> None:
    """Apply one logged operation (recovery) as it was applied when it was logged."""
    if kind == st.WAL_STORE:
        clean, keys = validate_store(arrays_to_t(arr), mem.config, mem.schema, mem.expected_key_size,
                                     replay=True)
        if mem.schema is None:
            mem._init_schema(schema_of(clean))
        y, res = resolve_store(mem.index, mem.key_norm, keys)
        mem.wal_sequence = seq
        part = mem._apply_store(clean, y, res, keys)
        if "request" in arr:   # a chunk of a store whose answer the memory remembers
            mem.stores.replayed(mem, arr["request"], part)
    elif kind == st.WAL_COMMIT:
        mem.wal_sequence = seq
        mem.next_reduction_id += 1
        mem._apply_commit(-1, arr["ids"], arr["preds"], arr["in_tm"], arr["tm_key"], replay=True)
    else:
        raise st.SnapshotError(f"WAL record {seq}: unknown kind {kind}")


def _key_norm_meta(settings: dict) -> dict:
    """The key normaliser's settings a snapshot records and must match, from a config (as a dict) or a
    snapshot's meta (written before the option: none). With 'running' its growth and floor decide when
    the frozen map changes, so a WAL replayed on top of the snapshot must use the same ones."""
    if settings.get("key_normalisation", "none") == "none":
        return {"key_normalisation": "none"}
    return {k: settings.get(k) for k in ("key_normalisation", "key_norm_growth", "key_norm_min_std")}

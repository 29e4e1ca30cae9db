"""The memory's state in and out: snapshot arrays + metadata, restore, and WAL replay.

:class:`~.durability.Durability` writes and reads the files; these functions say what the state
of a :class:`~.memory.CompactMemory` is in them: the slot table's rows, TM and RTM order, the
schema, the configuration a snapshot must match and the counters (``COUNTERS``). Each takes the
memory and is called with its lock held (or during its construction, by recovery).
"""
from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from . import storage as st
from .durability import COUNTERS, arrays_to_t, check_counters
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
    c, sch = mem.config, mem.schema
    meta = {"schema": None if sch is None else
            {**sch, "obs_shape": list(sch["obs_shape"]), "action_shape": list(sch["action_shape"])},
            "history_length": c.history_length, "delta": c.delta, "frame_scale": c.frame_scale,
            **_key_norm_meta(c),
            "counters": {k: int(getattr(mem, k)) for k in COUNTERS}}
    return arrays, meta


def restore_state(mem: CompactMemory, arrays: dict[str, np.ndarray], meta: dict) -> None:
    """Replace mem's state by a snapshot's; SnapshotError (state untouched) if it does not fit."""
    c = mem.config
    if meta.get("history_length") != c.history_length or meta.get("delta") != c.delta or \
            meta.get("frame_scale") != c.frame_scale:
        raise st.SnapshotError("snapshot was written with a different delta, frame_scale or "
                               "history_length than this memory's configuration")
    if _key_norm_meta(meta) != _key_norm_meta(c):
        raise st.SnapshotError(f"snapshot was written with key normalisation {_key_norm_meta(meta)}, this memory "
                               f"is configured with {_key_norm_meta(c)}")
    sch = meta.get("schema")
    if sch is not None and mem.expected_key_size is not None and sch["key_size"] != mem.expected_key_size:
        raise st.SnapshotError(f"snapshot key size {sch['key_size']} differs from {mem.expected_key_size}")
    check_counters(arrays, meta)
    mem._reset_state()
    for k, v in meta["counters"].items():
        setattr(mem, k, int(v))
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
        nkeys = mem.key_norm.apply(keys)
        y = mem.index.project(nkeys)
        res = mem.index.resolve(nkeys, y)
        mem.wal_sequence = seq
        mem._apply_store(clean, y, res, keys)
    elif kind == st.WAL_COMMIT:
        mem.wal_sequence = seq
        mem.next_reduction_id += 1
        mem._apply_commit(-1, arr["ids"], arr["preds"], arr["in_tm"], arr["tm_key"], replay=True)
    else:
        raise st.SnapshotError(f"WAL record {seq}: unknown kind {kind}")


def _key_norm_meta(c) -> dict:
    """The key normaliser's settings a snapshot records and must match (a config or a snapshot's meta;
    snapshots written before the option: none). With 'running' its growth and floor decide when the
    frozen map changes, so a WAL replayed on top of the snapshot must use the same ones."""
    get = (lambda k, d: c.get(k, d)) if isinstance(c, dict) else (lambda k, d: getattr(c, k))
    mode = get("key_normalisation", "none")
    if mode == "none":
        return {"key_normalisation": "none"}
    return {"key_normalisation": mode, "key_norm_growth": float(get("key_norm_growth", 0.0)),
            "key_norm_min_std": float(get("key_norm_min_std", 0.0))}

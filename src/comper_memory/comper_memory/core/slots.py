"""SlotTable: the columnar per-identity storage of the memory.

Every identity (a similar-transition set) lives in one slot of preallocated, growable numpy
columns (``a[name][slot]``): its representative transition, its value-label history (a ring
of ``history_length``), its count, first/last step, last store sequence, TM order key, RTM
prediction and lease. Identity ids are int64, allocated in increasing order and never reused;
slots are reused (a free list). ``ids_sorted``/``slots_sorted`` map live ids to slots (ids
increasing, so a lookup is a binary search).

A representative's observations are columns of their own (:class:`~.frames.ObsColumns`): whole, or with a
frame layout (``frame_store``) frame ids into a :class:`~.frames.FrameStore` that holds each distinct frame once.

The table is also the index's :class:`~comper_memory.core.similarity.KeySource`: an identity's
key is rebuilt from its representative (and scaled by the memory's
:class:`~.key_norm.KeyNormaliser`), so no key is stored twice. Not thread-safe: the
memory holds the lock.
"""
from __future__ import annotations

from typing import Callable

import numpy as np

from comper_msgs_py.arrays import Transitions

from .frames import FrameLayout, ObsColumns
from .key_norm import KeyNormaliser
from .keys import transition_keys

__all__ = ["SlotTable", "SLOT_FIELDS"]

# the slot columns as snapshots hold them (hist_total == count, kept for the format); the observations'
# columns are ObsColumns'
SLOT_FIELDS = ("id", "rewards", "terminated", "truncated", "episode_id", "hist", "hist_total",
               "count", "first_step", "last_step", "last_seq", "tm_key", "rtm_pred", "lease", "actions")
# representative columns written when an identity is created: (Transitions field, column)
_REP_COLUMNS = (("actions", "actions"),
                ("rewards", "rewards"), ("terminated", "terminated"), ("truncated", "truncated"),
                ("episode_ids", "episode_id"), ("steps", "first_step"))


class SlotTable:
    """Columns ``a`` indexed by slot, the free list, and the live id <-> slot map."""

    def __init__(self, history_length: int, frame_scale: float, key_norm: KeyNormaliser | None = None):
        self.H = int(history_length)
        self.frame_scale = frame_scale
        self.key_norm = key_norm if key_norm is not None else KeyNormaliser()
        self.schema: dict | None = None
        self.obs: ObsColumns | None = None      # set with the schema (set_schema)
        self.cap = 0
        self.a: dict[str, np.ndarray] = {}
        self.free: list[int] = []
        self.hi = 0                        # slots ever used (slots >= hi are fresh)
        # live ids (increasing) and their slots: growable buffers (1.25x), views below
        self._ids_buf = np.zeros(0, dtype=np.int64)
        self._slots_buf = np.zeros(0, dtype=np.int32)
        self._n_sorted = 0
        self.on_grow: list[Callable[[int], None]] = []   # called with the new capacity

    # ------------------------------------------------------------------ columns
    def set_schema(self, schema: dict, layout: FrameLayout | None) -> None:
        """The observations' shapes, and whether they are kept as frame ids (``layout``) or in the table."""
        self.schema = schema
        self.obs = ObsColumns(schema["obs_shape"], schema["obs_dtype"], layout)

    def _field_spec(self) -> dict[str, tuple[tuple, np.dtype, object]]:
        s = self.schema
        return {**self.obs.columns(), 
            "id": ((), np.int64, -1), "rewards": ((), np.float32, 0), "terminated": ((), bool, False),
            "truncated": ((), bool, False), "episode_id": ((), np.uint64, 0),
            "hist": ((self.H,), np.float32, 0),
            "count": ((), np.int64, 0), "first_step": ((), np.uint64, 0), "last_step": ((), np.uint64, 0),
            "last_seq": ((), np.int64, 0), "tm_key": ((), np.int64, 0), "rtm_pred": ((), np.float32, 0),
            "lease": ((), np.int32, -1),
            "actions": (tuple(s["action_shape"]), np.dtype(s["action_dtype"]), 0),
        }

    def _grow(self, need: int) -> None:
        if need <= self.cap:
            return
        new = max(need, self.cap + self.cap // 4, 1024)  # 1.25x: little slack
        for name, (shape, dtype, fill) in self._field_spec().items():
            arr = np.full((new,) + shape, fill, dtype=dtype)
            if name in self.a:
                arr[:self.cap] = self.a[name][:self.cap]
            self.a[name] = arr
        for hook in self.on_grow:
            hook(new)
        self.cap = new

    def alloc(self, k: int) -> np.ndarray:
        """k free slots (reused ones first)."""
        take = min(k, len(self.free))
        out = np.empty(k, dtype=np.int32)
        if take:
            out[:take] = self.free[len(self.free) - take:]
            del self.free[len(self.free) - take:]
        rest = k - take
        if rest:
            self._grow(self.hi + rest)
            out[take:] = np.arange(self.hi, self.hi + rest)
            self.hi += rest
        return out

    # ------------------------------------------------------------------ id <-> slot
    @property
    def ids_sorted(self) -> np.ndarray:
        """Live identity ids, increasing (a view)."""
        return self._ids_buf[:self._n_sorted]

    @property
    def slots_sorted(self) -> np.ndarray:
        """Slots of :attr:`ids_sorted` (a view)."""
        return self._slots_buf[:self._n_sorted]

    @property
    def n_live(self) -> int:
        return self._n_sorted

    def set_sorted(self, ids: np.ndarray, slots: np.ndarray) -> None:
        self._ids_buf = np.ascontiguousarray(ids, dtype=np.int64)
        self._slots_buf = np.ascontiguousarray(slots, dtype=np.int32)
        self._n_sorted = len(ids)

    def _append_sorted(self, ids: np.ndarray, slots: np.ndarray) -> None:
        n, k = self._n_sorted, len(ids)
        if n + k > len(self._ids_buf):
            cap = max(n + k, n + n // 4, 1024)
            ib = np.zeros(cap, np.int64)
            sb = np.zeros(cap, np.int32)
            ib[:n], sb[:n] = self._ids_buf[:n], self._slots_buf[:n]
            self._ids_buf, self._slots_buf = ib, sb
        self._ids_buf[n:n + k] = ids
        self._slots_buf[n:n + k] = slots
        self._n_sorted = n + k

    def slots_of(self, ids: np.ndarray) -> np.ndarray:
        """Slots of ids (-1 where the id is not live)."""
        ids = np.asarray(ids, dtype=np.int64)
        pos = np.searchsorted(self.ids_sorted, ids)
        pos_c = np.minimum(pos, max(len(self.ids_sorted) - 1, 0))
        ok = (pos < len(self.ids_sorted)) & (self.ids_sorted[pos_c] == ids) if len(self.ids_sorted) else \
            np.zeros(len(ids), dtype=bool)
        return np.where(ok, self.slots_sorted[pos_c] if len(self.slots_sorted) else -1, -1)

    # ------------------------------------------------------------------ KeySource
    def live_ids(self) -> np.ndarray:
        return self.ids_sorted

    def keys_of(self, ids: np.ndarray) -> np.ndarray:
        return self.keys_of_slots(self.slots_of(ids))

    def alive(self, ids: np.ndarray) -> np.ndarray:
        return self.slots_of(ids) >= 0

    # ------------------------------------------------------------------ identities
    def keys_of_slots(self, slots: np.ndarray) -> np.ndarray:
        return self.key_norm.apply(self.raw_keys_of_slots(slots))

    def raw_keys_of_slots(self, slots: np.ndarray) -> np.ndarray:
        """Keys [s, a, r, s'] of the identities in ``slots`` before the key normaliser."""
        a = self.a
        s, s2 = self.obs.get(a, slots)
        t = Transitions(s, a["actions"][slots], a["rewards"][slots], s2, a["terminated"][slots],
                        a["truncated"][slots])
        return transition_keys(t, self.frame_scale)

    def create(self, ids: np.ndarray, t: Transitions, rows: np.ndarray) -> np.ndarray:
        """New identities ``ids`` (increasing, above every live id) represented by ``t[rows]``;
        returns their slots."""
        slots = self.alloc(len(ids))
        if len(ids):
            a = self.a
            a["id"][slots] = ids
            for f_src, f_dst in _REP_COLUMNS:
                a[f_dst][slots] = getattr(t, f_src)[rows]
            self.obs.put(a, slots, t.states[rows], t.next_states[rows])
            a["count"][slots] = 0
            a["lease"][slots] = -1
            a["rtm_pred"][slots] = 0
            self._append_sorted(ids, slots)
        return slots

    def record(self, tslot: np.ndarray, labels: np.ndarray, steps: np.ndarray,
               seq0: int) -> tuple[np.ndarray, np.ndarray]:
        """Append transition i (store sequence seq0 + i) to the set in slot tslot[i], in order:
        its label into the history ring, count, last step and sequence. Returns (updated slots,
        sequence of each one's first transition of this batch)."""
        a = self.a
        n = len(tslot)
        seq = seq0 + np.arange(n, dtype=np.int64)
        order = np.argsort(tslot, kind="stable")
        ss = tslot[order]
        first = np.ones(n, dtype=bool)
        first[1:] = ss[1:] != ss[:-1]
        gstart = np.flatnonzero(first)
        gsize = np.diff(np.append(gstart, n))
        useg = ss[gstart]
        rank = np.arange(n) - np.repeat(gstart, gsize)
        gs_rep = np.repeat(gsize, gsize)
        keep = rank >= gs_rep - self.H
        tot = a["count"][ss] + rank
        a["hist"][ss[keep], tot[keep] % self.H] = labels[order][keep]
        a["count"][useg] += gsize
        last = gstart + gsize - 1
        a["last_seq"][useg] = seq[order][last]
        a["last_step"][useg] = steps[order][last]
        return useg, seq[order][gstart]

    def remove(self, slots: np.ndarray) -> np.ndarray:
        """Drop the identities in ``slots`` (unique); returns their ids."""
        a = self.a
        ids = a["id"][slots].copy()
        self.obs.drop(a, slots)
        keep = ~np.isin(self.ids_sorted, ids)
        self.set_sorted(self.ids_sorted[keep], self.slots_sorted[keep])
        a["id"][slots] = -1
        a["lease"][slots] = -1
        self.free.extend(slots.tolist())
        return ids

    # ------------------------------------------------------------------ reading
    def newest_labels(self, slots: np.ndarray) -> np.ndarray:
        a = self.a
        return a["hist"][slots, (a["count"][slots] - 1) % self.H]

    def histories(self, slots: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(labels oldest -> newest of each set, concatenated; their lengths)."""
        a = self.a
        k = len(slots)
        lens = np.minimum(a["count"][slots], self.H)
        tot = a["count"][slots]
        ridx = np.repeat(np.arange(k), lens)
        off = np.arange(int(lens.sum())) - np.repeat(np.cumsum(lens) - lens, lens)
        pos = (np.repeat(tot - lens, lens) + off) % self.H
        return a["hist"][slots[ridx], pos], lens

    def reps(self, slots: np.ndarray, labels: np.ndarray) -> Transitions:
        a = self.a
        s, s2 = self.obs.get(a, slots)
        return Transitions(s, a["actions"][slots], a["rewards"][slots], s2, a["terminated"][slots],
                           a["truncated"][slots],
                           value_labels=labels.astype(np.float32), episode_ids=a["episode_id"][slots],
                           steps=a["first_step"][slots])

    def rows(self) -> dict[str, np.ndarray]:
        """The snapshot columns of the live identities, ordered by id; with a frame layout the frame ids and
        the frame store's frames instead of the observations."""
        slots = self.slots_sorted
        # snapshot format unchanged: hist_total == count
        out = {name: self.a["count" if name == "hist_total" else name][slots] for name in SLOT_FIELDS}
        return {**out, **self.obs.rows(self.a, slots)}

    def load_rows(self, arrays: dict[str, np.ndarray], written: FrameLayout | None = None) -> np.ndarray:
        """Fill an empty table from snapshot columns (ids increasing); returns the slots. ``written``: the frame
        layout the snapshot holds (None: observations), converted if it is not this table's (ObsColumns.load).
        """
        ids = arrays["id"]
        slots = self.alloc(len(ids))
        for name in SLOT_FIELDS:
            if name != "hist_total":  # equals count (kept in the snapshot for its format)
                self.a[name][slots] = arrays[name]
        self.obs.load(self.a, slots, arrays, written)
        self.set_sorted(ids.astype(np.int64), slots)
        return slots

    def bytes_used(self) -> int:
        return (sum(arr.nbytes for arr in self.a.values()) + self._ids_buf.nbytes +
                self._slots_buf.nbytes + 8 * len(self.free) +
                (self.obs.bytes_used() if self.obs is not None else 0))


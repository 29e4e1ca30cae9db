"""Durability of one memory: its WAL, its snapshot directory, and recovery at start-up.

``Durability`` owns ``storage_dir``: appending a record before an operation is acknowledged,
a checkpoint (snapshot, then a new log file, then the old ones deleted) every
``snapshot_every`` operations, and at start-up: finishing or undoing an interrupted snapshot
write, loading the snapshot and replaying the log after it. The file formats are in
:mod:`.storage`; what a snapshot holds is checked here (:func:`check_arrays`, :func:`check_counters`).
The memory supplies its state as callbacks (its snapshot arrays, its log sequence; at start-up:
restore from a snapshot, apply one logged record), so this module knows nothing of slots or
tables.
"""
from __future__ import annotations

import glob
import os
import shutil
from typing import Callable

import numpy as np

from comper_msgs_py.arrays import Transitions

from . import storage as st
from .config import MemoryConfig
from .slots import SLOT_FIELDS

__all__ = ["Durability", "COUNTERS", "check_counters", "check_arrays", "t_to_arrays", "arrays_to_t"]

# the memory's counters, as a snapshot's metadata holds them
COUNTERS = ("next_id", "next_reduction_id", "transitions_stored", "similarity_hits",
            "reductions", "sets_reduced", "evictions", "wal_sequence")
_T_FIELDS = ("states", "actions", "rewards", "next_states", "terminated", "truncated",
             "value_labels", "episode_ids", "steps")


def t_to_arrays(t: Transitions) -> dict[str, np.ndarray]:
    """A store's WAL record."""
    return {f: getattr(t, f) for f in _T_FIELDS}


def arrays_to_t(arr: dict[str, np.ndarray]) -> Transitions:
    return Transitions(**{f: arr[f] for f in _T_FIELDS})


def check_counters(arrays: dict[str, np.ndarray], meta: dict) -> None:
    """SnapshotError unless the metadata's counters agree with the arrays (a hand-edited
    next_id would hand out ids that exist already; format-1 manifests carry no checksum of
    their own)."""
    c = meta.get("counters")
    if not isinstance(c, dict) or any(not isinstance(c.get(k), int) or c[k] < 0 for k in COUNTERS):
        raise st.SnapshotError("snapshot counters are missing or negative")
    ids = arrays.get("id")
    if ids is not None and len(ids):
        if c["next_id"] <= int(ids.max()) or len(np.unique(ids)) != len(ids):
            raise st.SnapshotError(f"snapshot metadata next_id {c['next_id']} does not exceed the "
                                   f"largest identity id {int(ids.max())} (or ids repeat)")
        if c["transitions_stored"] < int(arrays["count"].sum()):
            raise st.SnapshotError("snapshot metadata transitions_stored is below the stored counts")


def check_arrays(arrays: dict[str, np.ndarray]) -> None:
    """SnapshotError unless every slot column and both table orders are there, one row each."""
    if not arrays:
        return
    missing = [f for f in SLOT_FIELDS + ("tm_order", "rtm_order") if f not in arrays]
    if missing:
        raise st.SnapshotError(f"snapshot lacks arrays {missing}")
    n = len(arrays["id"])
    bad = [f for f in SLOT_FIELDS if len(arrays[f]) != n]
    if bad:
        raise st.SnapshotError(f"snapshot arrays {bad} do not have {n} rows")


class Durability:
    """The WAL and snapshots in ``config.storage_dir``."""

    def __init__(self, config: MemoryConfig, log: Callable[[str], None], *,
                 state: Callable[[], tuple[dict, dict]], sequence: Callable[[], int]):
        """state() -> (arrays, meta) of a snapshot; sequence() -> the last logged operation."""
        self.config = config
        self._log = log
        self._state, self._sequence = state, sequence
        self._wal: st.WriteAheadLog | None = None
        self.checkpoint_sequence = 0   # wal sequence of the last checkpoint

    @property
    def snapshot_dir(self) -> str:
        return os.path.join(self.config.storage_dir, "snapshot")

    def _wal_files(self) -> list[str]:
        return sorted(glob.glob(os.path.join(self.config.storage_dir, "wal-*.log")))

    def open(self, restore: Callable[[dict, dict], None], apply: Callable[[int, int, dict], None]) -> None:
        """Recover: restore(arrays, meta) from the snapshot, apply(seq, kind, arrays) for each
        logged operation after it; then open the log for appending."""
        d, sequence = self.config.storage_dir, self._sequence
        os.makedirs(d, exist_ok=True)
        self._recover_snapshot_dir()
        if os.path.lexists(self.snapshot_dir):
            arrays, meta = st.read_snapshot(self.snapshot_dir)
            check_arrays(arrays)
            restore(arrays, meta)
            self.checkpoint_sequence = sequence()
        self._replay_wal(apply)
        files = self._wal_files()
        path = files[-1] if files else os.path.join(d, f"wal-{sequence() + 1:016d}.log")
        self._wal = st.WriteAheadLog(path, self.config.durability)

    def _recover_snapshot_dir(self) -> None:
        """Finish or undo a snapshot write that a kill interrupted (storage_dir only).

        A checkpoint writes ``snapshot.tmp-<pid>``, renames ``snapshot`` to ``snapshot.old-<pid>``,
        renames the new one into place and deletes the old one; the log files it makes redundant
        are deleted only after that. So: no ``snapshot`` but an old one -> the kill fell between
        the two renames, the old one (the last good snapshot) goes back into place and the log
        replays over it. Leftover tmp/old directories holding only snapshot files are removed;
        anything else with such a name is left alone (with a warning)."""
        snap = self.snapshot_dir
        olds = sorted(glob.glob(glob.escape(snap) + ".old-*"))
        tmps = sorted(glob.glob(glob.escape(snap) + ".tmp-*"))
        if not os.path.lexists(snap) and olds:
            good = []
            for o in olds:
                try:
                    _, meta = st.read_snapshot(o)
                    good.append((int(meta["counters"]["wal_sequence"]), o))
                except (st.SnapshotError, KeyError, TypeError, ValueError):
                    continue
            if good:
                _, best = max(good)
                os.rename(best, snap)
                self._log(f"storage: the last snapshot write was interrupted; restored the previous "
                          f"snapshot {os.path.basename(best)} -> snapshot (the log replays over it)")
                olds.remove(best)
        for left in olds + tmps:
            if st.is_snapshot_dir(left) or (os.path.isdir(left) and not os.path.islink(left) and
                                            set(os.listdir(left)) <= {"manifest.json", "state.npz"}):
                st.remove_snapshot_dir(left)
                self._log(f"storage: removed {os.path.basename(left)}, left by an interrupted snapshot write")
            else:
                self._log(f"storage: {left} is not a snapshot leftover; left untouched")

    def _replay_wal(self, apply: Callable[[int, int, dict], None]) -> None:
        """Replay every log file after the snapshot: loud about damage, never silently lossy."""
        sequence = self._sequence
        files = self._wal_files()
        for i, path in enumerate(files):
            scan = st.scan_wal(path)
            last = i == len(files) - 1
            damaged = scan.damage == "corrupt" or (scan.damage == "torn" and not last)
            later = files[i + 1:]
            if damaged:
                later_records = sum(len(st.scan_wal(p).records) for p in later)
                if not self.config.wal_accept_loss:
                    more = (f" {later_records} more records are in {len(later)} later log files."
                            if later else "")
                    raise scan.corrupt_error(
                        f"{more} To start anyway and lose the damaged record and everything after "
                        f"it, restart once with -p wal_accept_loss:=true (MemoryConfig("
                        f"wal_accept_loss=True)); the damaged file is then copied to "
                        f"{os.path.basename(path)}.damaged-{scan.good_end} first.")
            for seq, kind, arr in scan.records:
                if seq <= sequence():
                    continue
                if seq != sequence() + 1:
                    raise st.SnapshotError(f"WAL {path}: record {seq} follows {sequence()} (gap)")
                apply(seq, kind, arr)
            if damaged:
                keep = f"{path}.damaged-{scan.good_end}"
                shutil.copy2(path, keep)
                st.truncate_wal(path, scan.good_end)
                for p in later:
                    os.rename(p, p + ".discarded")
                self._log(f"storage: wal_accept_loss: dropped the damaged record at byte offset "
                          f"{scan.good_end} of {path} and {scan.records_after} intact records after it"
                          f"{f' plus {len(later)} later log files (renamed *.discarded)' if later else ''}; "
                          f"the damaged file is kept as {keep}; replayed up to sequence {sequence()}")
                return
            if scan.damage == "torn":
                st.truncate_wal(path, scan.good_end)
                self._log(f"storage: dropped a torn last record of {path} ({scan.size - scan.good_end} "
                          f"bytes at offset {scan.good_end}: the process stopped while writing it, so "
                          f"it was never acknowledged); replayed up to sequence {sequence()}")

    def append(self, seq: int, kind: int, arrays: dict[str, np.ndarray]) -> None:
        """Log operation ``seq`` (before it is applied and acknowledged)."""
        self._wal.append(seq, kind, arrays)

    def maybe_checkpoint(self) -> None:
        """A checkpoint if snapshot_every operations were logged since the last one."""
        every = self.config.snapshot_every
        if self._wal is not None and every and self._sequence() - self.checkpoint_sequence >= every:
            self.checkpoint()

    def checkpoint(self) -> None:
        """Snapshot into storage_dir, then rotate the WAL (older files are deleted)."""
        st.write_snapshot(self.snapshot_dir, *self._state())
        sequence = self._sequence()
        old = self._wal_files()
        self._wal.close()
        self._wal = st.WriteAheadLog(os.path.join(self.config.storage_dir,
                                                  f"wal-{sequence + 1:016d}.log"),
                                     self.config.durability)
        for p in old:
            if p != self._wal.path:
                os.remove(p)
        self.checkpoint_sequence = sequence

    def close(self) -> None:
        if self._wal is not None:
            self._wal.close()
            self._wal = None

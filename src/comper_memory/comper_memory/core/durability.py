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
from .frames import FRAMES_ARRAY, FrameLayout, pack_obs, unpack_obs
from .slots import SLOT_FIELDS

__all__ = ["Durability", "COUNTERS", "check_counters", "check_arrays", "t_to_arrays", "arrays_to_t"]

# the memory's counters, as a snapshot's metadata holds them
COUNTERS = ("next_id", "next_reduction_id", "transitions_stored", "similarity_hits",
            "reductions", "sets_reduced", "evictions", "wal_sequence")
_T_FIELDS = ("states", "actions", "rewards", "next_states", "terminated", "truncated",
             "value_labels", "episode_ids", "steps")


def t_to_arrays(t: Transitions, layout: FrameLayout | None = None) -> dict[str, np.ndarray]:
    """A store's WAL record; with a frame layout its observations as distinct frames and indices (pack_obs)."""
    if layout is None:
        return {f: getattr(t, f) for f in _T_FIELDS}
    return {**{f: getattr(t, f) for f in _T_FIELDS if f not in ("states", "next_states")},
            **pack_obs(layout, t.states, t.next_states)}


def arrays_to_t(arr: dict[str, np.ndarray]) -> Transitions:
    if FRAMES_ARRAY in arr:
        states, next_states = unpack_obs(arr)
        arr = {**arr, "states": states, "next_states": next_states}
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


def _first_sequence(path: str) -> int | None:
    """The first sequence a log file was opened for (its name: wal-<sequence>.log); None if unknown."""
    try:
        return int(os.path.basename(path)[4:-4])
    except ValueError:
        return None


def _seqs(a: int, b: int) -> str:
    """'acknowledged operation 5 is' or '3 acknowledged operations (sequences 5-7) are'."""
    if a == b:
        return f"acknowledged operation {a} is"
    return f"{b - a + 1} acknowledged operations (sequences {a}-{b}) are"


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
        accepted = self._replay_wal(apply)
        files = self._wal_files()
        path = files[-1] if files else os.path.join(d, f"wal-{sequence() + 1:016d}.log")
        self._wal = st.WriteAheadLog(path, self.config.durability)
        if accepted:   # the damaged or short log is replaced by a snapshot of what was replayed (and the mark)
            self.checkpoint()
        else:
            self._write_mark("start")

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

    def _replay_wal(self, apply: Callable[[int, int, dict], None]) -> bool:
        """Replay every log file after the snapshot: loud about damage, never silently lossy.

        Everything is read and checked before anything changes: damage other than a torn tail of
        the last file (storage.scan_wal), and a log that ends before the sequence its mark
        records, stop start-up (files unchanged) unless ``wal_accept_loss``. Then the records are
        applied; with ``wal_accept_loss`` every intact record, before and after the damage, is
        replayed, each damaged file is copied to ``<file>.damaged-<offset>``, and True is returned
        (also for an accepted short log): the caller then checkpoints, which replaces the log files. A torn tail is copied to
        ``<file>.torn-<offset>`` and cut."""
        accept = self.config.wal_accept_loss
        start = self._sequence()
        files = self._wal_files()
        # a file followed by one that starts at or before the snapshot's next sequence is wholly in
        # the snapshot (a kill fell between a checkpoint's snapshot and its deleting the old files)
        files = [p for p, q in zip(files, files[1:])
                 if _first_sequence(q) is None or _first_sequence(q) > start + 1] + files[-1:]
        scans = [st.scan_wal(p) for p in files]
        damaged = [s.damage == "corrupt" or (s.damage == "torn" and i < len(scans) - 1)
                   for i, s in enumerate(scans)]
        fix = (" To start anyway, restart once with -p wal_accept_loss:=true (MemoryConfig("
               "wal_accept_loss=True)): the intact records before and after the damage are replayed, "
               "the damaged bytes dropped, and the file is copied to <file>.damaged-<offset> first.")
        if not accept:
            for i, scan in enumerate(scans):
                if damaged[i]:
                    later = scans[i + 1:]
                    more = (f" {sum(len(s.records) for s in later)} more records are in {len(later)} later "
                            f"log files." if later else "")
                    whole = (" Only record headers are damaged in this file and every payload checks out: "
                             "accepting loses nothing." if not scan.lost else "")
                    raise scan.corrupt_error(more + whole + fix)
        mark = self._read_mark(accept)
        # the records to apply, in order, and the sequences that damage took out
        cur = start
        plan, gaps = [], []
        lost_before = False
        for path, scan in zip(files, scans):
            for (seq, kind, arr), (a, _) in zip(scan.records, scan.spans):
                if seq <= cur:
                    continue
                if seq != cur + 1:
                    if not (lost_before or any(x < a for x, _ in scan.lost)):
                        raise st.SnapshotError(f"WAL {path}: record {seq} follows {cur} (gap)")
                    gaps.append((cur + 1, seq - 1))
                plan.append((seq, kind, arr))
                cur = seq
            lost_before = lost_before or bool(scan.lost)
        # a log file wal-<n>.log was opened when the log had reached n - 1: a mark too
        named = max(files, key=lambda p: _first_sequence(p) or 0, default=None)
        if named is not None and (_first_sequence(named) or 1) - 1 > max(cur, mark["sequence"] if mark else -1):
            mark = {"file": os.path.basename(named), "sequence": _first_sequence(named) - 1,
                    "bytes": 0, "when": "checkpoint (as its file name says)"}
        missing = None
        if mark is not None and mark["sequence"] > cur:
            missing = self._missing(mark, cur, start)
            if not accept:
                raise st.WalMissingError(
                    f"{missing} Start-up stopped and nothing was changed. Put the missing log back (e.g. "
                    f"from a backup) and restart, or restart once with -p wal_accept_loss:=true "
                    f"(MemoryConfig(wal_accept_loss=True)) to start from sequence {cur} without them.",
                    reached=cur, expected=mark["sequence"])
        for seq, kind, arr in plan:
            apply(seq, kind, arr)
        for i, (path, scan) in enumerate(zip(files, scans)):
            if damaged[i]:
                keep = f"{path}.damaged-{scan.good_end}"
                shutil.copy2(path, keep)
                self._log(f"storage: wal_accept_loss: {path}: {scan.describe()}; replayed its "
                          f"{len(scan.records)} intact records ({len(scan.repaired)} with a damaged header) and "
                          f"dropped {sum(b - a for a, b in scan.lost)} damaged bytes; the file is kept as {keep} "
                          f"and replaced by a checkpoint")
            elif scan.damage == "torn":
                keep = st.cut_torn_tail(path, scan.good_end)
                self._log(f"storage: dropped a torn last record of {path} ({scan.size - scan.good_end} "
                          f"bytes at offset {scan.good_end}: the process stopped while writing it, so "
                          f"it was never acknowledged; the bytes are kept as {keep})")
        if gaps or missing or any(damaged):
            n = sum(b - a + 1 for a, b in gaps)
            seqs = ", ".join(f"{a}" if a == b else f"{a}-{b}" for a, b in gaps)
            tail = ""
            if mark is not None and mark["sequence"] > cur:
                tail = f"; {missing}"
            elif any(d and s.lost and s.lost[-1][1] == s.size and not s.records_after
                     for d, s in zip(damaged, scans)):
                tail = f"; damaged records after sequence {cur} at the end of a log file are lost (count unknown)"
            caveat = (" Identities created after a dropped store can have other ids than first acknowledged "
                      "(the replay runs without it)." if n else "")
            dropped = f"{n} logged operation{'s' * (n != 1)}" + (f" (sequence{'s' * (n != 1)} {seqs})" if n else "")
            self._log(f"storage: wal_accept_loss: dropped {dropped}{tail}; replayed {len(plan)} records up to "
                      f"sequence {cur}.{caveat}")
        return any(damaged) or missing is not None

    def _read_mark(self, accept: bool) -> dict | None:
        try:
            return st.read_mark(self.config.storage_dir)
        except st.SnapshotError as e:
            if not accept:
                raise st.SnapshotError(f"{e}. Start-up stopped and nothing was changed; restart once with "
                                       "-p wal_accept_loss:=true to start without the check (a new mark "
                                       "is written)") from None
            self._log(f"storage: wal_accept_loss: {e}; started without checking the log against it")
            return None

    def _missing(self, mark: dict, reached: int, start: int) -> str:
        path = os.path.join(self.config.storage_dir, mark["file"])
        now = (f"it is now {os.path.getsize(path)} bytes" if os.path.exists(path) else "it is missing")
        return (f"WAL: the log ends at sequence {reached} (snapshot: {start}), but at the last "
                f"{mark['when']} it had reached sequence {mark['sequence']} ({mark['file']}, "
                f"{mark['bytes']} bytes; {now}): {_seqs(reached + 1, mark['sequence'])} "
                f"missing.")

    def _write_mark(self, when: str) -> None:
        """The mark after the log's bytes are on disk (storage.write_mark)."""
        size = self._wal.sync()
        st.write_mark(self.config.storage_dir, self._wal.path, self._sequence(), size, when)

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
        self._write_mark("checkpoint")

    def close(self) -> None:
        """Close the log; a clean stop records the sequence it reached (``wal.mark``)."""
        if self._wal is not None:
            try:
                self._write_mark("stop")
            except OSError as e:
                self._log(f"storage: could not write {st.MARK_FILE} at stop ({e}); the next start "
                          "checks the log against the previous mark only")
            self._wal.close()
            self._wal = None

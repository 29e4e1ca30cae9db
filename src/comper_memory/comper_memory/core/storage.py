"""File formats of the memory's durability: write-ahead log and checksummed snapshots (no pickles).

WAL file: a sequence of records ``MAGIC | u32 payload length | u32 crc32(payload) | payload``
with payload ``u64 sequence | u8 kind | u32 header length | JSON header | raw array bytes``.
A record is written (and flushed / fsynced, per ``durability``) before the operation it logs
is acknowledged.

Replay (:func:`scan_wal`) tells two kinds of damage apart:

* a **torn tail**: the last record of the file is incomplete (the header or the payload runs past
  the end of the file, or the bytes there are not a record) and no intact record follows it. A
  process killed mid-write leaves exactly this; the record was never acknowledged, so it is
  dropped (the caller truncates it and logs a warning).
* **corruption**: a damaged record (bad magic, CRC mismatch, undecodable) with an intact record
  after it, or a complete last record whose CRC fails (it was written in full, so it was
  acknowledged). Replay stops with :class:`WalCorruptError` (offset, records after it); the file
  is left as it is until the user accepts the loss explicitly.

Snapshot: a directory with ``state.npz`` (numpy arrays, written and read with
``allow_pickle=False``) and ``manifest.json`` (format version, metadata, sha256 and size of
``state.npz``, and the sha256 of the manifest's own canonical JSON, so the metadata (counters
such as ``next_id``) is covered too). It is written into a temporary directory next to the
target and renamed into place. An existing target is replaced only when it is itself a snapshot
directory (its files are ``manifest.json`` and ``state.npz`` and nothing else); anything else is
refused and left untouched. A snapshot whose checksums, size or manifest do not match is refused
with :class:`SnapshotError` before anything is loaded.
"""
from __future__ import annotations

import hashlib
import json
import os
import struct
import zlib
from dataclasses import dataclass, field
from typing import Iterator

import numpy as np

__all__ = ["WriteAheadLog", "read_wal", "scan_wal", "WalScan", "WalCorruptError", "write_snapshot",
           "read_snapshot", "is_snapshot_dir", "SnapshotError", "WAL_STORE", "WAL_COMMIT"]

MAGIC = b"CMW1"
_HEAD = struct.Struct("<4sII")
_PAY = struct.Struct("<QBI")
WAL_STORE = 1
WAL_COMMIT = 2
SNAPSHOT_FORMAT = 2          # 2: manifest_sha256 covers the manifest; 1 (read only): it did not
_SNAPSHOT_FILES = {"manifest.json", "state.npz"}
_MAX_RECORD = 1 << 31        # a length field above this is damage, not a record


class SnapshotError(RuntimeError):
    """A snapshot is missing, corrupted, truncated or incompatible, or a snapshot path is not
    acceptable; nothing was loaded or replaced."""


class WalCorruptError(SnapshotError):
    """A WAL record in the middle of the log is damaged; replay stopped, the file is unchanged."""

    def __init__(self, message: str, *, path: str, offset: int, records_after: int,
                 first_seq_after: int | None):
        super().__init__(message)
        self.path = path
        self.offset = offset
        self.records_after = records_after
        self.first_seq_after = first_seq_after


def encode_arrays(seq: int, kind: int, arrays: dict[str, np.ndarray]) -> bytes:
    header, blobs = [], []
    for name, arr in arrays.items():
        arr = np.ascontiguousarray(arr)
        header.append([name, arr.dtype.str, list(arr.shape)])
        blobs.append(arr.tobytes())
    hj = json.dumps(header).encode()
    payload = _PAY.pack(seq, kind, len(hj)) + hj + b"".join(blobs)
    return _HEAD.pack(MAGIC, len(payload), zlib.crc32(payload)) + payload


def decode_payload(payload, copy: bool = True) -> tuple[int, int, dict[str, np.ndarray]]:
    """copy=False: the arrays are read-only views into ``payload`` (bytes or memoryview)."""
    seq, kind, hlen = _PAY.unpack_from(payload, 0)
    off = _PAY.size
    header = json.loads(bytes(payload[off:off + hlen]))
    off += hlen
    out = {}
    for name, dt, shape in header:
        dtype = np.dtype(dt)
        if dtype.hasobject:
            raise ValueError("object arrays are not allowed in the WAL")
        count = int(np.prod(shape, dtype=np.int64))
        nbytes = count * dtype.itemsize
        if off + nbytes > len(payload):
            raise ValueError("array runs past the record")
        arr = np.frombuffer(payload, dtype=dtype, count=count, offset=off).reshape(shape)
        out[name] = arr.copy() if copy else arr
        off += nbytes
    if off != len(payload):
        raise ValueError("trailing bytes in the record")
    return seq, kind, out


class WriteAheadLog:
    """Append-only log file; ``append`` returns once the record is durable per ``durability``."""

    def __init__(self, path: str, durability: str = "flush"):
        self.path = path
        self.durability = durability
        self._f = open(path, "ab", buffering=1 << 16)

    def append(self, seq: int, kind: int, arrays: dict[str, np.ndarray]) -> None:
        self._f.write(encode_arrays(seq, kind, arrays))
        if self.durability != "none":
            self._f.flush()
            if self.durability == "fsync":
                os.fsync(self._f.fileno())

    def close(self) -> None:
        if not self._f.closed:
            self._f.flush()
            if self.durability == "fsync":
                os.fsync(self._f.fileno())
            self._f.close()


def _record_at(data: bytes, off: int):
    """(status, end, record): status 'ok', 'short' (runs past the end of data) or 'bad'."""
    if off + _HEAD.size > len(data):
        return "short", len(data), None
    magic, length, crc = _HEAD.unpack_from(data, off)
    if magic != MAGIC or length > _MAX_RECORD or length < _PAY.size:
        return "bad", off, None
    end = off + _HEAD.size + length
    if end > len(data):
        return "short", len(data), None
    payload = data[off + _HEAD.size:end]   # a memoryview: no copy of the record
    if zlib.crc32(payload) != crc:
        return "bad", end, None
    try:
        return "ok", end, decode_payload(payload, copy=False)
    except Exception:  # noqa: BLE001 - a record that does not decode is damage
        return "bad", end, None


def _records_after(data: bytes, start: int) -> tuple[int, int | None]:
    """Intact records found after a damaged spot (resynchronising on the magic), first sequence."""
    n, first = 0, None
    raw = data.obj if isinstance(data, memoryview) else data   # bytes, for find()
    pos = raw.find(MAGIC, start)
    while pos >= 0:
        status, end, rec = _record_at(data, pos)
        if status == "ok":
            n += 1
            first = rec[0] if first is None else first
            pos = end if raw[end:end + 4] == MAGIC else raw.find(MAGIC, end)
        else:
            pos = raw.find(MAGIC, pos + 1)
    return n, first


@dataclass
class WalScan:
    """What :func:`scan_wal` found in one WAL file."""
    path: str
    size: int
    records: list = field(default_factory=list)   # (sequence, kind, arrays) of the intact prefix
                                                   # (read-only views into the file's bytes)
    good_end: int = 0                              # byte offset after the last intact record
    damage: str | None = None                      # None, 'torn' or 'corrupt'
    records_after: int = 0                         # intact records after the damaged spot
    first_seq_after: int | None = None

    def corrupt_error(self, hint: str = "") -> WalCorruptError:
        seqs = (f" (sequences from {self.first_seq_after})" if self.first_seq_after is not None else "")
        last = self.records[-1][0] if self.records else None
        return WalCorruptError(
            f"WAL {self.path}: damaged record at byte offset {self.good_end} of {self.size} "
            f"(after sequence {last}); {self.records_after} intact records follow it{seqs}. "
            f"Start-up stopped and the file was not changed.{hint}",
            path=self.path, offset=self.good_end, records_after=self.records_after,
            first_seq_after=self.first_seq_after)


def scan_wal(path: str) -> WalScan:
    """Read a WAL file without changing it: the intact prefix and what ends it (module docstring)."""
    with open(path, "rb") as f:
        data = memoryview(f.read())
    scan = WalScan(path, len(data))
    off = 0
    while off < len(data):
        status, end, rec = _record_at(data, off)
        if status == "ok":
            scan.records.append(rec)
            off = end
            continue
        scan.good_end = off
        n_after, first = _records_after(data, off + 1)
        scan.records_after, scan.first_seq_after = n_after, first
        if n_after == 0 and (status == "short" or (status == "bad" and end == off)):
            scan.damage = "torn"   # incomplete or not a record, nothing intact after it
        else:
            scan.damage = "corrupt"  # a complete record failed its CRC, or intact records follow
        return scan
    scan.good_end = off
    return scan


def read_wal(path: str, *, repair: bool = True) -> Iterator[tuple[int, int, dict[str, np.ndarray]]]:
    """Yield (sequence, kind, arrays) of each intact record. A torn tail ends the iteration (and
    is truncated with repair=True); a corrupt record raises :class:`WalCorruptError`, file unchanged."""
    scan = scan_wal(path)
    if scan.damage == "corrupt":
        raise scan.corrupt_error()
    yield from scan.records
    if repair and scan.damage == "torn":
        truncate_wal(path, scan.good_end)


def truncate_wal(path: str, size: int) -> None:
    with open(path, "r+b") as f:
        f.truncate(size)
        f.flush()
        os.fsync(f.fileno())


def _sha256_file(path: str) -> tuple[str, int]:
    h = hashlib.sha256()
    size = 0
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
            size += len(chunk)
    return h.hexdigest(), size


def _manifest_digest(manifest: dict) -> str:
    body = {k: v for k, v in manifest.items() if k != "manifest_sha256"}
    return hashlib.sha256(json.dumps(body, sort_keys=True, separators=(",", ":")).encode()).hexdigest()


def _fsync_dir(path: str) -> None:
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def is_snapshot_dir(path: str) -> bool:
    """A real directory (not a link) holding only snapshot files, with a manifest of ours (any
    readable format); the only kind of directory :func:`write_snapshot` replaces."""
    if os.path.islink(path) or not os.path.isdir(path):
        return False
    try:
        names = set(os.listdir(path))
    except OSError:
        return False
    if not names <= _SNAPSHOT_FILES or "manifest.json" not in names:
        return False
    try:
        with open(os.path.join(path, "manifest.json")) as f:
            m = json.load(f)
    except (OSError, ValueError):
        return False
    return isinstance(m, dict) and "state_sha256" in m and "format" in m


def remove_snapshot_dir(path: str) -> None:
    """Delete a directory only if it holds nothing but snapshot files (never anything else)."""
    if os.path.islink(path) or not os.path.isdir(path):
        return
    names = os.listdir(path)
    if not set(names) <= _SNAPSHOT_FILES:
        return
    for n in names:
        os.remove(os.path.join(path, n))
    os.rmdir(path)


def write_snapshot(path: str, arrays: dict[str, np.ndarray], meta: dict) -> None:
    """Write a snapshot directory (temp dir + rename). An existing ``path`` is replaced only if it
    is a snapshot directory (:func:`is_snapshot_dir`); otherwise SnapshotError and nothing changes."""
    path = os.path.abspath(path)
    if os.path.lexists(path) and not is_snapshot_dir(path):
        raise SnapshotError(f"snapshot path {path!r} exists and is not a snapshot directory "
                            "(only manifest.json + state.npz); refusing to replace it")
    parent = os.path.dirname(path)
    os.makedirs(parent, exist_ok=True)
    tmp = f"{path}.tmp-{os.getpid()}"
    if os.path.lexists(tmp):
        if not os.path.isdir(tmp) or os.path.islink(tmp) or not set(os.listdir(tmp)) <= _SNAPSHOT_FILES:
            raise SnapshotError(f"snapshot: {tmp!r} exists and is not a leftover of a snapshot write")
        remove_snapshot_dir(tmp)
    os.makedirs(tmp)
    npz = os.path.join(tmp, "state.npz")
    with open(npz, "wb") as f:
        np.savez(f, **arrays)
        f.flush()
        os.fsync(f.fileno())
    digest, size = _sha256_file(npz)
    manifest = {"format": SNAPSHOT_FORMAT, "state_sha256": digest, "state_bytes": size,
                "arrays": sorted(arrays), "meta": meta}
    manifest["manifest_sha256"] = _manifest_digest(manifest)
    with open(os.path.join(tmp, "manifest.json"), "w") as f:
        json.dump(manifest, f, indent=1, sort_keys=True)
        f.flush()
        os.fsync(f.fileno())
    _fsync_dir(tmp)
    old = None
    if os.path.lexists(path):
        old = f"{path}.old-{os.getpid()}"
        if os.path.lexists(old):
            remove_snapshot_dir(old)
        if os.path.lexists(old):
            raise SnapshotError(f"snapshot: {old!r} exists and is not a snapshot directory")
        os.rename(path, old)
    os.rename(tmp, path)
    _fsync_dir(parent)
    if old:
        remove_snapshot_dir(old)


def read_snapshot(path: str) -> tuple[dict[str, np.ndarray], dict]:
    """Read and verify a snapshot; raise SnapshotError (nothing loaded) on any mismatch."""
    mpath = os.path.join(path, "manifest.json")
    npz = os.path.join(path, "state.npz")
    try:
        with open(mpath) as f:
            manifest = json.load(f)
    except (OSError, ValueError) as e:
        raise SnapshotError(f"snapshot {path!r}: cannot read manifest.json ({e})") from None
    if not isinstance(manifest, dict) or manifest.get("format") not in (1, SNAPSHOT_FORMAT):
        raise SnapshotError(f"snapshot {path!r}: unknown manifest format")
    if manifest["format"] >= 2 and manifest.get("manifest_sha256") != _manifest_digest(manifest):
        raise SnapshotError(f"snapshot {path!r}: manifest.json checksum mismatch (the metadata was "
                            "edited or corrupted)")
    try:
        digest, size = _sha256_file(npz)
    except OSError as e:
        raise SnapshotError(f"snapshot {path!r}: cannot read state.npz ({e})") from None
    if size != manifest.get("state_bytes") or digest != manifest.get("state_sha256"):
        raise SnapshotError(f"snapshot {path!r}: state.npz checksum mismatch (corrupted or truncated)")
    try:
        with np.load(npz, allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files}
    except Exception as e:  # noqa: BLE001 - any decoding problem means a bad snapshot
        raise SnapshotError(f"snapshot {path!r}: cannot decode state.npz ({e})") from None
    if sorted(arrays) != manifest.get("arrays"):
        raise SnapshotError(f"snapshot {path!r}: arrays differ from the manifest")
    if not isinstance(manifest.get("meta"), dict):
        raise SnapshotError(f"snapshot {path!r}: manifest has no metadata")
    return arrays, manifest["meta"]

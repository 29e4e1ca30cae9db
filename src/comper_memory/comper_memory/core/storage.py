"""File formats of the memory's durability: write-ahead log, its mark, and checksummed snapshots (no pickles).

WAL file: a sequence of records ``MAGIC | u32 payload length | u32 crc32(payload) | payload``
with payload ``u64 sequence | u8 kind | u32 header length | JSON header | raw array bytes``.
A record is written (and flushed / fsynced, per ``durability``) before the operation it logs
is acknowledged.

Replay (:func:`scan_wal`) reads the whole file and tells the kinds of damage apart:

* an **intact record**: magic, length and CRC check out and the payload decodes.
* a **damaged header**: the 12 header bytes are wrong (magic or length) but the bytes after them
  form a complete payload whose CRC matches the header's CRC field (the record ends at its length,
  at the next intact record or at the end of the file). The record was written in full; it is
  listed as repaired (its payload is intact) and the file counts as corrupt.
* **lost bytes**: a range that holds no intact record (a CRC mismatch, a record that does not
  decode, unrecognisable bytes). The scan resynchronises on the next intact record (the magic
  followed by a record whose CRC matches) and goes on, so every intact record after the damage
  is found.
* a **torn tail**: the only damage is the end of the file, and those bytes are the beginning of a
  record that runs past the end (magic and length as written, payload incomplete). A process
  killed mid-write leaves exactly this; the record was never acknowledged. Anything else is
  **corruption**.

WAL mark (``wal.mark`` in the storage directory, :func:`write_mark` / :func:`read_mark`): the
log file, the sequence the log had reached and the file's size, written atomically (and
checksummed) when the log is opened, at each checkpoint and at a clean stop. A log that ends
before the mark's sequence lost acknowledged operations (the file was emptied or cut).

Snapshot: a directory with ``state.npz`` (numpy arrays, written and read with
``allow_pickle=False``) and ``manifest.json`` (format version, metadata, sha256 and size of
``state.npz``, and the sha256 of the manifest's own canonical JSON, so the metadata (counters
such as ``next_id``) is covered too). It is written into a temporary directory next to the
target and renamed into place. An existing target is replaced only when it is itself a snapshot
directory (its files are ``manifest.json`` and ``state.npz`` and nothing else); anything else is
refused and left untouched. A snapshot whose checksums, size or manifest do not match is refused
with :class:`SnapshotError` before anything is loaded.

Size: the memory's whole on-disk format (log records and their scan, the log's mark, snapshots)
with the checks that refuse damage; the durability logic that uses them is in :mod:`.durability`.
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

__all__ = ["WriteAheadLog", "read_wal", "scan_wal", "WalScan", "WalCorruptError", "WalMissingError",
           "write_snapshot", "read_snapshot", "is_snapshot_dir", "SnapshotError", "WAL_STORE", "WAL_COMMIT",
           "MARK_FILE", "read_mark", "write_mark"]

MAGIC = b"CMW1"
_HEAD = struct.Struct("<4sII")
_PAY = struct.Struct("<QBI")
WAL_STORE = 1
WAL_COMMIT = 2
SNAPSHOT_FORMAT = 2          # 2: manifest_sha256 covers the manifest; 1 (read only): it did not
_SNAPSHOT_FILES = {"manifest.json", "state.npz"}
_MAX_RECORD = 1 << 31        # a length field above this is damage, not a record
_MAX_ENDS = 64               # payload ends tried for a record whose header is damaged
MARK_FILE = "wal.mark"
MAP_MEMBER_BYTES = 1 << 28   # state.npz members this large are mapped, not read (read_snapshot)
MARK_FORMAT = 1


class SnapshotError(RuntimeError):
    """A snapshot is missing, corrupted, truncated or incompatible, or a snapshot path is not
    acceptable; nothing was loaded or replaced."""


class WalCorruptError(SnapshotError):
    """A WAL file is damaged (not only a torn tail); replay stopped, the file is unchanged."""

    def __init__(self, message: str, *, path: str, offset: int, records_after: int,
                 first_seq_after: int | None):
        super().__init__(message)
        self.path = path
        self.offset = offset
        self.records_after = records_after
        self.first_seq_after = first_seq_after


class WalMissingError(SnapshotError):
    """The log ends before the sequence its mark records: acknowledged operations are missing."""

    def __init__(self, message: str, *, reached: int, expected: int):
        super().__init__(message)
        self.reached = reached
        self.expected = expected


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

    def sync(self) -> int:
        """Write everything to disk (whatever ``durability``); the file's size."""
        self._f.flush()
        os.fsync(self._f.fileno())
        return os.fstat(self._f.fileno()).st_size

    def close(self) -> None:
        if not self._f.closed:
            self._f.flush()
            if self.durability == "fsync":
                os.fsync(self._f.fileno())
            self._f.close()


def _record_at(data, off: int):
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


def _next_intact(data, raw: bytes, start: int) -> int:
    """Offset of the first intact record at or after ``start`` (the magic, then a record whose
    CRC matches and which decodes), or the end of the data."""
    pos = raw.find(MAGIC, start)
    while pos >= 0:
        if _record_at(data, pos)[0] == "ok":
            return pos
        pos = raw.find(MAGIC, pos + 1)
    return len(data)


def _with_damaged_header(data, raw: bytes, off: int, limit: int):
    """(end, record) when the bytes from off + 12 up to some end <= limit are a complete payload
    whose CRC matches the header's CRC field (magic or length damaged, payload intact); else None.
    Ends tried: the one the length field gives, each later magic, ``limit``."""
    first = off + _HEAD.size + _PAY.size
    if first > limit:
        return None
    _, length, crc = _HEAD.unpack_from(data, off)
    ends = {limit}
    if off + _HEAD.size + length <= limit:
        ends.add(off + _HEAD.size + length)
    pos = raw.find(MAGIC, first)
    while 0 <= pos < limit and len(ends) < _MAX_ENDS:
        ends.add(pos)
        pos = raw.find(MAGIC, pos + 1)
    for end in sorted(e for e in ends if e >= first):
        payload = data[off + _HEAD.size:end]
        if zlib.crc32(payload) == crc:
            try:
                return end, decode_payload(payload, copy=False)
            except Exception:  # noqa: BLE001 - a CRC match that does not decode is no record
                continue
    return None


def _torn_prefix(data, off: int) -> bool:
    """The bytes from off to the end are the start of one record that runs past the end: what a
    write cut short leaves (magic and length as written, the payload incomplete)."""
    k = len(data) - off
    head = bytes(data[off:off + _HEAD.size])
    if head[:4] != MAGIC[:min(4, k)]:
        return False
    if k < _HEAD.size:
        return True
    _, length, _ = _HEAD.unpack_from(head, 0)
    return _PAY.size <= length <= _MAX_RECORD and off + _HEAD.size + length > len(data)


def _peek(data, start: int, end: int) -> str:
    """What a damaged range's first header claims (unverified), for the report; '' if nothing."""
    try:
        if data[start:start + 4] != MAGIC or end - start < _HEAD.size + _PAY.size:
            return ""
        seq, kind, hlen = _PAY.unpack_from(data, start + _HEAD.size)
        p = start + _HEAD.size + _PAY.size
        if hlen > end - p:
            return ""
        header = json.loads(bytes(data[p:p + hlen]))
        rows = {name: shape for name, _, shape in header}
        n = rows.get("rewards") or rows.get("states")   # one row per transition (frame records: no states)
        if kind == WAL_STORE and n:
            return f"its unverified header says sequence {seq}, a store of {int(n[0])} transitions"
        if kind == WAL_COMMIT and rows.get("ids"):
            return f"its unverified header says sequence {seq}, a reduction commit of {int(rows['ids'][0])} identities"
        return f"its unverified header says sequence {seq}"
    except Exception:  # noqa: BLE001 - a hint only
        return ""


@dataclass
class WalScan:
    """What :func:`scan_wal` found in one WAL file."""
    path: str
    size: int
    records: list = field(default_factory=list)   # (sequence, kind, arrays) of every intact record, in
                                                   # file order (read-only views into the file's bytes)
    spans: list = field(default_factory=list)     # (start, end) byte range of each record
    repaired: list = field(default_factory=list)  # indices into records: header damaged, payload intact
    lost: list = field(default_factory=list)      # (start, end) byte ranges holding no intact record
    hints: list = field(default_factory=list)     # per lost range: what its header claims ('' if nothing)
    damage: str | None = None                      # None, 'torn' or 'corrupt'
    good_end: int = 0                              # end of the intact prefix (offset of the first damage)
    records_after: int = 0                         # intact records that start after the first damage
    first_seq_after: int | None = None

    @property
    def prefix(self) -> int:
        """Number of records before the first damage."""
        return sum(1 for s, _ in self.spans if s < self.good_end)

    def describe(self) -> str:
        """The damage in words: each lost byte range and each record whose header was damaged."""
        parts = []
        for (a, b), hint in zip(self.lost, self.hints):
            before = [r[0] for (s, _), r in zip(self.spans, self.records) if s < a]
            after = [r[0] for (s, _), r in zip(self.spans, self.records) if s >= b]
            where = (f"between sequences {before[-1] if before else 'start'} and "
                     f"{after[0] if after else 'end of file'}")
            parts.append(f"bytes {a}-{b} ({b - a} bytes, {where}) hold no intact record"
                         + (f" ({hint})" if hint else ""))
        for i in self.repaired:
            a, b = self.spans[i]
            parts.append(f"the record at bytes {a}-{b} (sequence {self.records[i][0]}) has a damaged header "
                         f"but its payload checks out (CRC)")
        return "; ".join(parts)

    def corrupt_error(self, hint: str = "") -> WalCorruptError:
        seqs = (f" (sequences from {self.first_seq_after})" if self.first_seq_after is not None else "")
        before = [r[0] for (s, _), r in zip(self.spans, self.records) if s < self.good_end]
        last = before[-1] if before else None
        return WalCorruptError(
            f"WAL {self.path}: damaged record at byte offset {self.good_end} of {self.size} "
            f"(after sequence {last}); {self.records_after} intact records follow it{seqs}. "
            f"Damage: {self.describe()}. Start-up stopped and the file was not changed.{hint}",
            path=self.path, offset=self.good_end, records_after=self.records_after,
            first_seq_after=self.first_seq_after)


def scan_wal(path: str) -> WalScan:
    """Read a WAL file without changing it: every intact record and the damage between them
    (module docstring)."""
    with open(path, "rb") as f:
        raw = f.read()
    data = memoryview(raw)
    n = len(data)
    scan = WalScan(path, n)
    off = 0
    while off < n:
        status, end, rec = _record_at(data, off)
        if status != "ok":
            nxt = _next_intact(data, raw, off + 1)
            got = _with_damaged_header(data, raw, off, nxt)
            if got is None:
                scan.lost.append((off, nxt))
                scan.hints.append(_peek(data, off, nxt))
                off = nxt
                continue
            end, rec = got
            scan.repaired.append(len(scan.records))
        scan.records.append(rec)
        scan.spans.append((off, end))
        off = end
    starts = [a for a, _ in scan.lost] + [scan.spans[i][0] for i in scan.repaired]
    if not starts:
        scan.good_end = n
        return scan
    scan.good_end = min(starts)
    after = [r[0] for (s, _), r in zip(scan.spans, scan.records) if s > scan.good_end]
    scan.records_after = len(after)
    scan.first_seq_after = after[0] if after else None
    torn = (not scan.repaired and len(scan.lost) == 1 and scan.lost[0][1] == n
            and _torn_prefix(data, scan.lost[0][0]))
    scan.damage = "torn" if torn else "corrupt"
    return scan


def read_wal(path: str, *, repair: bool = True) -> Iterator[tuple[int, int, dict[str, np.ndarray]]]:
    """Yield (sequence, kind, arrays) of each intact record. A torn tail ends the iteration (and
    is truncated with repair=True, after a copy to ``<path>.torn-<offset>``); any other damage
    raises :class:`WalCorruptError`, file unchanged."""
    scan = scan_wal(path)
    if scan.damage == "corrupt":
        raise scan.corrupt_error()
    yield from scan.records
    if repair and scan.damage == "torn":
        cut_torn_tail(path, scan.good_end)


def truncate_wal(path: str, size: int) -> None:
    with open(path, "r+b") as f:
        f.truncate(size)
        f.flush()
        os.fsync(f.fileno())


def cut_torn_tail(path: str, offset: int) -> str:
    """Copy the bytes from ``offset`` to ``<path>.torn-<offset>`` (fsynced), then truncate the
    file there; the copy's path."""
    keep = f"{path}.torn-{offset}"
    with open(path, "rb") as f:
        f.seek(offset)
        tail = f.read()
    _write_durably(keep, tail)
    truncate_wal(path, offset)
    return keep


def _write_durably(path: str, data: bytes) -> None:
    with open(path, "wb") as f:
        f.write(data)
        f.flush()
        os.fsync(f.fileno())


def _mark_digest(body: dict) -> str:
    return hashlib.sha256(json.dumps(body, sort_keys=True, separators=(",", ":")).encode()).hexdigest()


def write_mark(storage_dir: str, wal_file: str, sequence: int, size: int, when: str) -> None:
    """Record atomically that the log ``wal_file`` reached ``sequence`` at ``size`` bytes (``when``:
    start, checkpoint or stop). Call it only once those bytes are on disk."""
    body = {"format": MARK_FORMAT, "file": os.path.basename(wal_file), "sequence": int(sequence),
            "bytes": int(size), "when": when}
    body["sha256"] = _mark_digest(body)
    path = os.path.join(storage_dir, MARK_FILE)
    _write_durably(path + ".new", json.dumps(body, sort_keys=True).encode())
    os.replace(path + ".new", path)
    _fsync_dir(storage_dir)


def read_mark(storage_dir: str) -> dict | None:
    """The mark (file, sequence, bytes, when), None if there is none; SnapshotError if damaged."""
    path = os.path.join(storage_dir, MARK_FILE)
    if not os.path.lexists(path):
        return None
    try:
        with open(path, "rb") as f:
            m = json.loads(f.read())
        ok = (isinstance(m, dict) and m.get("format") == MARK_FORMAT
              and m.get("sha256") == _mark_digest({k: v for k, v in m.items() if k != "sha256"})
              and isinstance(m.get("sequence"), int) and isinstance(m.get("bytes"), int)
              and isinstance(m.get("file"), str))
    except (OSError, ValueError) as e:
        raise SnapshotError(f"{path}: cannot read the log's mark ({e})") from None
    if not ok:
        raise SnapshotError(f"{path}: the log's mark is damaged (checksum or fields)")
    return m


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


def _member(npz: str, z, name: str) -> np.ndarray:
    """A member of a verified state.npz; a large uncompressed one as a read-only memory map of the file (a restore
    then copies it where it belongs without holding it twice, e.g. a frame store's frames)."""
    info = z.zip.getinfo(f"{name}.npy")
    if info.file_size < MAP_MEMBER_BYTES or info.compress_type != 0:
        return z[name]
    with open(npz, "rb") as f:
        f.seek(info.header_offset)
        local = f.read(30)
        if local[:4] != b"PK\x03\x04":
            raise ValueError(f"{info.filename}: no local file header")
        name_len, extra_len = struct.unpack("<HH", local[26:30])
        f.seek(info.header_offset + 30 + name_len + extra_len)
        version = np.lib.format.read_magic(f)
        read_header = np.lib.format.read_array_header_1_0 if version == (1, 0) else np.lib.format.read_array_header_2_0
        shape, fortran, dtype = read_header(f)
        if dtype.hasobject:
            raise ValueError(f"{info.filename}: object arrays are not allowed")
        offset = f.tell()
    return np.memmap(npz, dtype=dtype, mode="r", offset=offset, shape=shape, order="F" if fortran else "C")


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
            arrays = {k: _member(npz, z, k) for k in z.files}
    except Exception as e:  # noqa: BLE001 - any decoding problem means a bad snapshot
        raise SnapshotError(f"snapshot {path!r}: cannot decode state.npz ({e})") from None
    if sorted(arrays) != manifest.get("arrays"):
        raise SnapshotError(f"snapshot {path!r}: arrays differ from the manifest")
    if not isinstance(manifest.get("meta"), dict):
        raise SnapshotError(f"snapshot {path!r}: manifest has no metadata")
    return arrays, manifest["meta"]

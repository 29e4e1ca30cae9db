"""Crash-safe rosbag2 writing for the recorder (pure: rosbags only, no rclpy).

Size: the writer, its metadata and the repair of a bag cut by a crash belong together (repair
reads back what the writer's split protocol leaves); the recorder's config and topic parsing follow.

A bag is a rosbag2 directory (``metadata.yaml`` + storage files) written as a sequence of
**split files**, exactly like rosbag2's ``max_bagfile_size`` / ``max_bagfile_duration`` splitting:

    runs/<run_id>/bag/
        metadata.yaml          # lists only the *closed* files; rewritten atomically after each split
        bag_0.mcap             # each closed file is a complete MCAP (summary, schemas, index)
        bag_1.mcap
        .open/bag_2/bag_2.mcap # the file being written (not listed; lost or ignored after a crash)

Each file is written by a fresh ``rosbags.rosbag2.Writer`` in the hidden ``.open`` folder and,
when closed (size or duration reached, or on ``close()``), fsynced and renamed into the bag
folder; then ``metadata.yaml`` is rewritten (temp file + rename). A process killed with SIGKILL
therefore leaves a bag that opens with any rosbag2 reader and holds every message written up to
the last split (at most ``max_file_duration_s`` old). ``repair_bag`` rebuilds ``metadata.yaml``
from the complete files present (e.g. after a kill between the rename and the metadata update).

Files are zstd-compressed by default (MCAP chunk compression, as ``ros2 bag record`` writes it;
sqlite3: rosbag2 per-message compression) and every MCAP chunk carries the CRC32 of its records
(``_CrcMcapWriter``: rosbags writes 0, "no CRC"), which readers verify; ``check_mcap_file`` finds a
damaged chunk and its byte offset.

Types: ``comper_typestore()`` is the ROS 2 Jazzy typestore of rosbags plus the comper_msgs
types parsed from the installed ``.msg`` files. ``Writer.add_connection`` embeds the full
definition (nested ``comper_msgs/Array``, ``std_msgs/Header``, ``builtin_interfaces/Time``) in
every file (MCAP schema records / sqlite3 ``message_definitions``), and the RIHS01 hashes equal
the ones rosidl generates, so a reader needs nothing but the bag (``bag_typestore``).
"""
from __future__ import annotations

import mmap
import os
import shutil
import struct
import time
from binascii import crc32
from dataclasses import dataclass, field
from io import StringIO
from pathlib import Path

from rosbags.interfaces import (Qos, QosDurability, QosHistory, QosLiveliness, QosReliability,
                                QosTime)
from rosbags.rosbag2 import CompressionFormat, CompressionMode, StoragePlugin, Writer
from rosbags.rosbag2.metadata import dump_qos_v9
from rosbags.rosbag2.storage_mcap import McapWriter
from rosbags.typesys import Stores, get_types_from_idl, get_types_from_msg, get_typestore
from ruamel.yaml import YAML

__all__ = ["comper_typestore", "find_msg_dir", "bag_typestore", "ChunkedBagWriter", "repair_bag",
           "RecorderConfig", "parse_topic_spec", "bag_info",
           "TYPE_BY_SUFFIX", "DEFAULT_TOPICS", "write_metadata", "check_mcap_file", "FileCheck",
           "make_qos", "STORAGE_SUFFIX", "BAG_VERSION", "ROS_DISTRO", "COMPRESSIONS"]

BAG_VERSION = 9
#: written into metadata.yaml (and each MCAP file's embedded rosbag2 metadata) as ros_distro
ROS_DISTRO = "jazzy"
#: the recorder's `compression` choices (zstd: MCAP chunk compression, sqlite3 per-message compression)
COMPRESSIONS = ("zstd", "none")
STORAGE_SUFFIX = {"mcap": ".mcap", "sqlite3": ".db3"}
_PLUGIN = {"mcap": StoragePlugin.MCAP, "sqlite3": StoragePlugin.SQLITE3}
_OPEN_DIR = ".open"


# --------------------------------------------------------------------------------------------
# types
def find_msg_dir() -> Path:
    """The folder holding comper_msgs' installed .msg files (ament index, else the source tree)."""
    candidates = []
    try:
        from ament_index_python.packages import get_package_share_directory
        candidates.append(Path(get_package_share_directory("comper_msgs")) / "msg")
    except Exception:  # not installed / AMENT_PREFIX_PATH unset
        pass
    for prefix in filter(None, os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep)):
        candidates.append(Path(prefix) / "share" / "comper_msgs" / "msg")
    candidates.append(Path(__file__).resolve().parents[2] / "comper_msgs" / "msg")
    for c in candidates:
        if (c / "TransitionBatch.msg").is_file():
            return c
    raise FileNotFoundError("comper_msgs .msg files not found (source env.sh or build the workspace)")


_TYPESTORE = None


def comper_typestore(msg_dir: str | os.PathLike | None = None):
    """rosbags typestore: ROS 2 Jazzy standard types + every comper_msgs message (cached)."""
    global _TYPESTORE
    if _TYPESTORE is not None and msg_dir is None:
        return _TYPESTORE
    store = get_typestore(Stores.ROS2_JAZZY)
    typs = {}
    for f in sorted(Path(msg_dir or find_msg_dir()).glob("*.msg")):
        typs.update(get_types_from_msg(f.read_text(), f"comper_msgs/msg/{f.stem}"))
    store.register(typs)
    if msg_dir is None:
        _TYPESTORE = store
    return store


def bag_typestore(connections):
    """A typestore built ONLY from the definitions embedded in a bag's connections
    (``rosbags.rosbag2.Reader(...).connections``); checks the RIHS01 hashes."""
    from rosbags.interfaces import MessageDefinitionFormat
    store = get_typestore(Stores.EMPTY)
    typs = {}
    for c in connections:
        if c.msgdef.format == MessageDefinitionFormat.MSG:
            typs.update(get_types_from_msg(c.msgdef.data, c.msgtype))
        elif c.msgdef.format == MessageDefinitionFormat.IDL:
            sep = "=" * 80 + "\n"
            if c.msgdef.data.startswith(f"{sep}IDL: "):
                for part in c.msgdef.data.split(sep)[1:]:
                    typs.update(get_types_from_idl(part.split("\n", 1)[1]))
            else:
                typs.update(get_types_from_idl(c.msgdef.data))
        # else: a topic listed without messages carries no definition; nothing to decode
    store.register(typs)
    for c in connections:
        if c.msgtype in typs and c.digest and store.hash_rihs01(c.msgtype) != c.digest:
            raise ValueError(f"{c.msgtype}: embedded definition hash {store.hash_rihs01(c.msgtype)} "
                             f"!= recorded {c.digest}")
    return store


def make_qos(reliable: bool = True, depth: int = 100, transient_local: bool = False) -> Qos:
    """A rosbags Qos record (what goes into offered_qos_profiles)."""
    zero = QosTime(0, 0)
    return Qos(QosHistory.KEEP_LAST, int(depth),
               QosReliability.RELIABLE if reliable else QosReliability.BEST_EFFORT,
               QosDurability.TRANSIENT_LOCAL if transient_local else QosDurability.VOLATILE,
               zero, zero, QosLiveliness.AUTOMATIC, zero, False)


# --------------------------------------------------------------------------------------------
# storage files with chunk CRCs
_MCAP_MAGIC = b"\x89MCAP0\r\n"
_OP_FOOTER, _OP_CHUNK = 0x02, 0x06
_ZSTD_MAGIC = b"\x28\xb5\x2f\xfd"
# a chunk record: opcode (1), record length (8), then message_start_time, message_end_time,
# uncompressed_size (3 x uint64) and uncompressed_crc (uint32)
_CHUNK_CRC_OFFSET = 1 + 8 + 24


class _CrcMcapWriter(McapWriter):
    """rosbags' MCAP storage writer, with each chunk's ``uncompressed_crc`` filled in.

    rosbags writes 0 there, which MCAP defines as "no CRC", so a flipped byte inside a chunk went
    unnoticed by every reader. Here the CRC32 of the chunk's uncompressed records is patched into the
    chunk record once rosbags has written it; MCAP readers (rosbags' Reader, the MCAP library behind
    ``ros2 bag``) verify a non-zero CRC when they read the chunk. The rosbag2 metadata record embedded
    in the file names the distro (``ROS_DISTRO``) instead of ``rosbags``."""

    def close_chunk(self) -> None:
        with self.chunk.bio.getbuffer() as records:
            crc = crc32(records)
        start = self.bio.tell()
        super().close_chunk()
        end = self.bio.tell()
        self.bio.seek(start + _CHUNK_CRC_OFFSET)
        self.bio.write(struct.pack("<I", crc))
        self.bio.seek(end)

    def close(self, version: int, metadata: str) -> None:
        super().close(version, metadata.replace("ros_distro: rosbags", f"ros_distro: {ROS_DISTRO}"))


class _FileWriter(Writer):
    """rosbags' rosbag2 Writer with the CRC-writing MCAP storage (sqlite3 unchanged: it has no CRCs)."""
    STORAGE_PLUGINS = {**Writer.STORAGE_PLUGINS, StoragePlugin.MCAP: _CrcMcapWriter}


def _compression_mode(storage: str, compression: str) -> CompressionMode:
    """zstd in MCAP = chunk compression (what ``ros2 bag record -s mcap`` writes; metadata.yaml says no
    rosbag2-level compression); sqlite3 has no storage compression, so each message is compressed
    (rosbag2 ``compression_mode: message``, which ``ros2 bag`` reads too)."""
    if compression not in COMPRESSIONS:
        raise ValueError(f"compression {compression!r} is not one of {list(COMPRESSIONS)}")
    if compression == "none":
        return CompressionMode.NONE
    return CompressionMode.STORAGE if storage == "mcap" else CompressionMode.MESSAGE


def _metadata_compression(mode: CompressionMode) -> tuple[str, str]:
    """(compression_format, compression_mode) of metadata.yaml: only rosbag2-level compression counts."""
    if mode in (CompressionMode.NONE, CompressionMode.STORAGE):
        return "", ""
    return "zstd", mode.name.lower()


@dataclass
class FileCheck:
    """What :func:`check_mcap_file` found in one MCAP file."""
    path: Path
    chunks: int = 0            # chunk records read
    unverified: int = 0        # chunks written without a CRC (crc field 0: older recorders)
    damage: str = ""           # "" (intact), "crc" (a chunk's content changed), "truncated", "format"
    offset: int = -1           # byte offset of the damaged record
    detail: str = ""

    @property
    def ok(self) -> bool:
        return not self.damage


def check_mcap_file(path: str | os.PathLike) -> FileCheck:
    """Walk every record of an MCAP file and verify each chunk's CRC32 (after decompression).

    Returns the first damage with its byte offset: ``crc`` (a chunk does not decompress or its CRC does
    not match: bytes changed inside the messages), ``truncated`` (a record runs past the end, no footer:
    a file cut by a crash) or ``format`` (not an MCAP file). Chunks with CRC 0 count as ``unverified``."""
    from rosbags.rosbag2.storage_mcap import decompress
    path = Path(path)
    res = FileCheck(path)
    size = path.stat().st_size
    if size < 2 * len(_MCAP_MAGIC):
        res.damage, res.offset, res.detail = "truncated", 0, f"{size} bytes"
        return res
    with open(path, "rb") as f, mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ) as m:
        if m[:len(_MCAP_MAGIC)] != _MCAP_MAGIC:
            res.damage, res.offset, res.detail = "format", 0, "no MCAP magic"
            return res
        pos = len(_MCAP_MAGIC)
        while True:
            if pos + 9 > size:
                res.damage, res.offset, res.detail = "truncated", pos, "file ends inside a record header"
                return res
            op, length = m[pos], struct.unpack_from("<Q", m, pos + 1)[0]
            body = pos + 9
            if body + length > size:
                res.damage, res.offset, res.detail = "truncated", pos, f"record of {length} bytes runs past the end"
                return res
            if op == _OP_FOOTER:
                if m[size - len(_MCAP_MAGIC):] != _MCAP_MAGIC:
                    res.damage, res.offset, res.detail = "truncated", size, "no closing MCAP magic"
                return res
            if op == _OP_CHUNK:
                res.chunks += 1
                try:
                    usize, crc = struct.unpack_from("<QI", m, body + 16)
                    (nlen,) = struct.unpack_from("<I", m, body + 28)
                    compression = bytes(m[body + 32:body + 32 + nlen]).decode()
                    (clen,) = struct.unpack_from("<Q", m, body + 32 + nlen)
                    data_at = body + 40 + nlen
                    if data_at + clen > body + length:
                        raise ValueError(f"compressed size {clen} exceeds the chunk record")
                    if crc == 0:
                        res.unverified += 1
                    decompress(bytes(m[data_at:data_at + clen]), compression, usize, crc)
                except Exception as exc:  # noqa: BLE001 - ReaderError, ZstdError, a garbled header
                    res.damage, res.offset = "crc", pos
                    res.detail = f"{type(exc).__name__}: {str(exc).rstrip('.')}"
                    return res
            pos = body + length


# --------------------------------------------------------------------------------------------
# writer
@dataclass
class _Topic:
    name: str
    msgtype: str
    qos: list
    digest: str = ""
    count: int = 0           # messages in closed files


@dataclass
class _FileInfo:
    name: str
    start: int
    end: int
    count: int


@dataclass
class WriterStats:
    files_closed: int = 0
    messages: int = 0        # messages written (open file included)
    bytes: int = 0           # payload bytes written
    split_seconds: float = 0.0  # time spent closing files and rewriting metadata
    topic_counts: dict = field(default_factory=dict)


class ChunkedBagWriter:
    """A rosbag2 bag written as split files closed regularly (see module doc).

    storage: "mcap" (default, rosbag2's default since Iron) or "sqlite3".
    compression: "zstd" (default; MCAP: zstd chunks, sqlite3: zstd per message) or "none".
    max_file_size_bytes: split when the open file's payload reaches this (0 = never).
    max_file_duration_s: split when the open file is this old (0 = never); bounds what a crash loses.
    custom_data: strings written into metadata.yaml's custom_data (run id, algorithm, ...).
    """

    def __init__(self, path: str | os.PathLike, *, storage: str = "mcap", compression: str = "zstd", typestore=None,
                 max_file_size_bytes: int = 256 * 2**20, max_file_duration_s: float = 5.0,
                 fsync: bool = True, custom_data: dict | None = None, clock=time.monotonic):
        if storage not in _PLUGIN:
            raise ValueError(f"storage {storage!r} is not one of {sorted(_PLUGIN)}")
        self.path = Path(path)
        if self.path.exists() and any(self.path.iterdir()):
            raise FileExistsError(f"{self.path} exists and is not empty; a bag is never overwritten")
        self.path.mkdir(parents=True, exist_ok=True)
        (self.path / _OPEN_DIR).mkdir(exist_ok=True)
        self.storage = storage
        self.compression = compression
        self._compression_mode = _compression_mode(storage, compression)
        self.typestore = typestore if typestore is not None else comper_typestore()
        self.max_file_size_bytes = int(max_file_size_bytes)
        self.max_file_duration_s = float(max_file_duration_s)
        self.fsync = bool(fsync)
        self.custom_data = {str(k): str(v) for k, v in (custom_data or {}).items()}
        self._clock = clock
        self._topics: list[_Topic] = []
        self._files: list[_FileInfo] = []
        self._writer: Writer | None = None
        self._conns: dict[int, object] = {}      # topic handle -> rosbags Connection of the open file
        self._file_counts: dict[int, int] = {}
        self._file_bytes = 0
        self._file_opened = 0.0
        self._file_start = 2**63 - 1
        self._file_end = 0
        self._closed = False
        self.stats = WriterStats()
        self._write_metadata()  # an empty bag opens from the start

    # topics --------------------------------------------------------------------------------
    def add_topic(self, topic: str, msgtype: str, qos: list | None = None) -> int:
        """Register a topic; returns the handle for write(). msgtype like comper_msgs/msg/EpisodeSummary."""
        if msgtype not in self.typestore.fielddefs:
            raise KeyError(f"unknown message type {msgtype} (not in the typestore)")
        for i, t in enumerate(self._topics):
            if t.name == topic:
                if t.msgtype != msgtype:
                    raise ValueError(f"topic {topic} already recorded with type {t.msgtype}")
                return i
        self._topics.append(_Topic(topic, msgtype, list(qos or []),
                                   self.typestore.hash_rihs01(msgtype)))
        self.stats.topic_counts[topic] = 0
        return len(self._topics) - 1

    @property
    def topics(self) -> list[tuple[str, str]]:
        return [(t.name, t.msgtype) for t in self._topics]

    # writing -------------------------------------------------------------------------------
    def _open_file(self) -> None:
        name = f"bag_{len(self._files)}"
        staging = self.path / _OPEN_DIR / name
        if staging.exists():
            shutil.rmtree(staging)
        self._writer = _FileWriter(staging, version=BAG_VERSION, storage_plugin=_PLUGIN[self.storage])
        self._writer.set_compression(self._compression_mode, CompressionFormat.ZSTD)
        self._writer.open()
        self._conns = {}
        self._file_counts = {}
        self._file_bytes = 0
        self._file_opened = self._clock()
        self._file_start, self._file_end = 2**63 - 1, 0
        for h in range(len(self._topics)):   # every file embeds every definition
            self._connect(h)

    def _connect(self, handle: int):
        t = self._topics[handle]
        conn = self._writer.add_connection(t.name, t.msgtype, typestore=self.typestore,
                                           offered_qos_profiles=t.qos)
        self._conns[handle] = conn
        self._file_counts[handle] = 0
        return conn

    def write(self, handle: int, timestamp_ns: int, data: bytes | memoryview) -> None:
        """Append one CDR-serialised message (with its 4-byte encapsulation header)."""
        if self._closed:
            raise RuntimeError("bag writer is closed")
        if self._writer is None:
            self._open_file()
        conn = self._conns.get(handle)
        if conn is None:
            conn = self._connect(handle)
        self._writer.write(conn, int(timestamp_ns), data)
        n = len(data)
        self._file_counts[handle] += 1
        self._file_bytes += n
        self._file_start = min(self._file_start, int(timestamp_ns))
        self._file_end = max(self._file_end, int(timestamp_ns))
        self.stats.messages += 1
        self.stats.bytes += n
        self.stats.topic_counts[self._topics[handle].name] += 1
        if self.max_file_size_bytes and self._file_bytes >= self.max_file_size_bytes:
            self.split()

    def due(self) -> bool:
        """True when the open file is older than max_file_duration_s (call split())."""
        return (self._writer is not None and self.max_file_duration_s > 0
                and self._clock() - self._file_opened >= self.max_file_duration_s)

    def maybe_split(self) -> bool:
        if self.due():
            self.split()
            return True
        return False

    def split(self) -> None:
        """Close the open file (if it holds messages), move it into the bag, rewrite metadata."""
        if self._writer is None:
            return
        t0 = time.perf_counter()
        writer, self._writer = self._writer, None
        writer.close()
        staging = writer.path
        name = f"bag_{len(self._files)}{STORAGE_SUFFIX[self.storage]}"
        src = staging / f"{staging.name}{STORAGE_SUFFIX[self.storage]}"
        if self.fsync:
            with open(src, "rb+") as f:
                os.fsync(f.fileno())
        os.replace(src, self.path / name)
        shutil.rmtree(staging, ignore_errors=True)
        self._files.append(_FileInfo(name, self._file_start, self._file_end, sum(self._file_counts.values())))
        for h, c in self._file_counts.items():
            self._topics[h].count += c
        self._write_metadata()
        self.stats.files_closed += 1
        self.stats.split_seconds += time.perf_counter() - t0

    def close(self) -> None:
        if self._closed:
            return
        self.split()
        self._closed = True
        shutil.rmtree(self.path / _OPEN_DIR, ignore_errors=True)

    def __enter__(self) -> "ChunkedBagWriter":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # metadata ------------------------------------------------------------------------------
    def _write_metadata(self) -> None:
        write_metadata(self.path, self.storage, [(t.name, t.msgtype, t.qos, t.digest, t.count)
                                                 for t in self._topics],
                       self._files, self.custom_data, fsync=self.fsync,
                       compression=_metadata_compression(self._compression_mode))


def write_metadata(path: Path, storage: str, topics, files, custom_data: dict, *, fsync: bool = True,
                   compression: tuple[str, str] = ("", "")) -> None:
    """Write rosbag2 v9 metadata.yaml for `files` (atomic: temp file, fsync, rename).

    topics: (name, msgtype, qos list, rihs01, message count); files: _FileInfo-like records;
    compression: rosbag2-level (compression_format, compression_mode), ("zstd", "message") for a
    per-message compressed sqlite3 bag; MCAP chunk compression is the storage's own and not listed.
    """
    start = min((f.start for f in files if f.count), default=0)
    end = max((f.end for f in files if f.count), default=0)
    count = sum(f.count for f in files)
    info = {
        "version": BAG_VERSION,
        "storage_identifier": storage,
        "relative_file_paths": [f.name for f in files],
        "duration": {"nanoseconds": max(0, end - start)},
        "starting_time": {"nanoseconds_since_epoch": start},
        "message_count": count,
        "topics_with_message_count": [
            {"topic_metadata": {"name": name, "type": msgtype, "serialization_format": "cdr",
                                "offered_qos_profiles": dump_qos_v9(list(qos)),
                                "type_description_hash": digest},
             "message_count": n}
            for name, msgtype, qos, digest, n in topics],
        "compression_format": compression[0],
        "compression_mode": compression[1],
        "files": [{"path": f.name, "starting_time": {"nanoseconds_since_epoch": f.start if f.count else 0},
                   "duration": {"nanoseconds": max(0, f.end - f.start) if f.count else 0},
                   "message_count": f.count} for f in files],
        "custom_data": dict(custom_data) or None,
        "ros_distro": ROS_DISTRO,
    }
    yaml = YAML(typ="safe")
    yaml.default_flow_style = False
    buf = StringIO()
    yaml.dump({"rosbag2_bagfile_information": info}, buf)
    tmp = path / "metadata.yaml.tmp"
    with open(tmp, "w", encoding="utf8") as f:
        f.write(buf.getvalue())
        if fsync:
            f.flush()
            os.fsync(f.fileno())
    os.replace(tmp, path / "metadata.yaml")
    if fsync:
        try:
            fd = os.open(path, os.O_RDONLY)
            try:
                os.fsync(fd)
            finally:
                os.close(fd)
        except OSError:
            pass


def repair_bag(path: str | os.PathLike) -> dict:
    """Rebuild ``metadata.yaml`` of a split bag from the complete storage files present.

    Files that do not open or read to the end (the one being written when a process died, or one whose
    chunk CRC no longer matches: bytes changed on disk) are moved to ``<bag>/.open/`` untouched.
    Returns {"files": [...], "skipped": [...], "reasons": {skipped name: why}, "messages": n}.
    """
    from rosbags.rosbag2 import Reader
    path = Path(path)
    custom = {}
    storage = None
    compression = ("", "")
    meta = path / "metadata.yaml"
    if meta.exists():
        try:
            old = YAML(typ="safe").load(meta.read_text())["rosbag2_bagfile_information"]
            custom = old.get("custom_data") or {}
            storage = old.get("storage_identifier")
            compression = (old.get("compression_format") or "", old.get("compression_mode") or "")
        except Exception:
            pass
    cands = sorted((p for p in path.iterdir() if p.suffix in (".mcap", ".db3")),
                   key=lambda p: (int(p.stem.rsplit("_", 1)[-1]) if p.stem.rsplit("_", 1)[-1].isdigit() else 1 << 30, p.name))
    files, skipped, reasons, topics = [], [], {}, {}
    for p in cands:
        st = "mcap" if p.suffix == ".mcap" else "sqlite3"
        if storage is None:
            storage = st
        if st != storage:
            skipped.append(p.name)
            continue
        try:
            with Reader(p) as r:
                counts = {}
                lo, hi, n = 2**63 - 1, 0, 0
                conns = {c.id: c for c in r.connections}
                for c, ts, data in r.messages():
                    counts[c.topic] = counts.get(c.topic, 0) + 1
                    lo, hi, n = min(lo, ts), max(hi, ts), n + 1
                    if n == 1 and bytes(data[:4]) == _ZSTD_MAGIC:   # per-message zstd (CDR starts 00 01)
                        compression = ("zstd", "message")
                for c in conns.values():
                    t = topics.setdefault(c.topic, [c.topic, c.msgtype, list(c.ext.offered_qos_profiles), c.digest, 0])
                    t[4] += counts.get(c.topic, 0)
            files.append(_FileInfo(p.name, lo, hi, n))
        except Exception as exc:  # noqa: BLE001 - any reader failure: set the file aside, say why
            reasons[p.name] = _damage_reason(p, exc)
            (path / _OPEN_DIR).mkdir(exist_ok=True)
            os.replace(p, path / _OPEN_DIR / p.name)
            skipped.append(p.name)
    write_metadata(path, storage or "mcap", [tuple(v) for v in topics.values()], files, custom,
                   compression=compression)
    return {"files": [f.name for f in files], "skipped": skipped, "reasons": reasons,
            "messages": sum(f.count for f in files)}


def _damage_reason(p: Path, exc: Exception) -> str:
    """Why a storage file did not read: the MCAP check's finding with its offset, else the reader's error."""
    if p.suffix == ".mcap":
        chk = check_mcap_file(p)
        if chk.damage == "crc":
            return f"corrupt chunk at byte {chk.offset} ({chk.detail})"
        if chk.damage:
            return f"{chk.damage} at byte {chk.offset} ({chk.detail})"
    return f"{type(exc).__name__}: {str(exc).rstrip('.')}"


# --------------------------------------------------------------------------------------------
# recorder configuration (declared as ROS parameters by recorder_node)
from comper_msgs_py.params import param as _param  # noqa: E402  (pure: no rclpy)

DEFAULT_TOPICS = (
    "/comcact_node/transitions", "/comcact_node/episodes", "/comcact_node/evaluations",
    "/comper_node/transitions", "/comper_node/episodes", "/comper_node/evaluations",
    "/memory_node/stats", "/sim_node/episodes",
)

#: message type by the last part of a topic name (the topic contract, docs/recording.md)
TYPE_BY_SUFFIX = {
    "transitions": "comper_msgs/msg/TransitionBatch",
    "episodes": "comper_msgs/msg/EpisodeSummary",
    "evaluations": "comper_msgs/msg/EvaluationResult",
    "stats": "comper_msgs/msg/MemoryStats",
}


@dataclass(frozen=True)
class RecorderConfig:
    """Episode recorder (recorder_node): which topics, where, how the bag is split."""
    topics: list[str] = _param(
        list(DEFAULT_TOPICS),
        "topics to record; 'name' (type from the name's last part: transitions, episodes, "
        "evaluations, stats; otherwise discovered from the graph) or 'name:pkg/msg/Type'. "
        "Relative names resolve in the recorder's namespace")
    output_dir: str = _param("runs", "root of the run directories: <output_dir>/<run_id>/<bag_name>")
    run_id: str = _param("", "training run id (the run directory's name); empty = the start time, "
                             "YYYYmmdd-HHMMSS")
    bag_name: str = _param("bag", "name of the bag directory inside the run directory (bag_1, bag_2, "
                                  "... when it exists already)")
    algorithm: str = _param("", "algorithm label written into the bag's custom_data (evaluate groups by "
                                "it when no EvaluationResult names the algorithm)")
    storage: str = _param("mcap", "rosbag2 storage plugin", choices=("mcap", "sqlite3"))
    compression: str = _param(
        "zstd", "zstd: compressed bag as `ros2 bag record` writes it (mcap: zstd chunks, the MCAP storage's "
                "own compression; sqlite3: rosbag2 per-message zstd); none: uncompressed.",
        choices=COMPRESSIONS)
    max_file_size_mb: float = _param(256.0, "split the bag when the open file holds this many MB "
                                            "(rosbag2 max_bagfile_size); 0 = never", minimum=0.0)
    max_file_duration_s: float = _param(
        5.0, "split the bag when the open file is this old (rosbag2 max_bagfile_duration); each "
             "closed file is complete, so this bounds what a SIGKILL loses; 0 = never", minimum=0.0)
    fsync: bool = _param(True, "fsync each closed file and metadata.yaml (survives power loss, "
                               "not only process death)")
    qos_depth: int = _param(100, "history depth of the recorder's subscriptions", minimum=1)
    status_period_s: float = _param(
        0.02, "least seconds between two ~/status messages (RecorderStatus: messages written per topic, the "
              "publishers' flow control); one more goes out at close", minimum=0.0)
    discovery_period_s: float = _param(
        0.5, "period of the graph look-up for topics whose type is not known from their name",
        minimum=0.05)


def parse_topic_spec(spec: str) -> tuple[str, str | None]:
    """'name' or 'name:pkg/msg/Type' -> (name, msgtype or None); msgtype from the suffix map."""
    name, _, typ = spec.partition(":")
    name = name.strip()
    if typ:
        typ = typ.strip()
        if typ.count("/") == 1:
            pkg, t = typ.split("/")
            typ = f"{pkg}/msg/{t}"
        return name, typ
    return name, TYPE_BY_SUFFIX.get(name.rstrip("/").rsplit("/", 1)[-1])


def bag_info(path: str | os.PathLike) -> dict:
    """The bag's metadata.yaml (rosbag2_bagfile_information) as a dict."""
    return YAML(typ="safe").load((Path(path) / "metadata.yaml").read_text())["rosbag2_bagfile_information"]

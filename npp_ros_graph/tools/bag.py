"""Bags of npp runs: rosbag2 folders (metadata.yaml + one MCAP file) that any rosbag2 or MCAP reader opens.

Writing: the MCAP writer of the `mcap` package builds chunks in memory; at every flush the new records
go to the file in one write, followed by a provisional end (Data End, Footer without summary, magic)
that the next flush overwrites. So the file on disk is a complete MCAP as of the last flush, and a
recorder killed at any moment (SIGKILL included) leaves every message flushed before that readable;
metadata.yaml is replaced atomically at every flush too. Only a kill in the middle of a flush's own
write can tear the file's end: `repair` cuts it back to the last complete record.

Reading: rosbags' AnyReader, with the message definitions the bag carries (nothing from this machine's
interfaces is needed to decode a bag).

No ROS imports here: a bag can be written, repaired and read without rclpy.
"""

from __future__ import annotations

import os
import struct
import sys
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from io import StringIO
from pathlib import Path
from typing import Any, cast

from mcap.writer import CompressionType, IndexType, Writer
from rosbags.highlevel import AnyReader
from rosbags.interfaces import Qos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime
from rosbags.rosbag2.metadata import dump_qos_v9
from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from rosbags.typesys.store import Typestore
from ruamel.yaml import YAML

MAGIC = b"\x89MCAP0\r\n"
# Data End (crc 0: not computed) + Footer (no summary) + magic: what makes a flushed file a complete MCAP.
PROVISIONAL_END = struct.pack("<BQI", 0x0F, 4, 0) + struct.pack("<BQQQI", 0x02, 20, 0, 0, 0) + MAGIC
METADATA = "metadata.yaml"
BAG_VERSION = 9  # rosbag2 metadata version of ROS 2 Jazzy
INTERFACE_PACKAGES = ("npp_interfaces",)


class BagError(RuntimeError):
    """A bag cannot be written or read; the message says why and what to do."""


# ----------------------------------------------------------------------------- message definitions
def _msg_dirs(package: str) -> list[Path]:
    """Where `package`'s .msg files may be: each ament prefix's share folder, then this repository's msgs_py."""
    prefixes = [p for p in os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep) if p] + [sys.prefix]
    dirs = [Path(p) / "share" / package / "msg" for p in prefixes]
    dirs.append(Path(__file__).resolve().parents[2] / "msgs_py" / package / "msg")
    return [d for d in dirs if d.is_dir()]


_TYPESTORE: Typestore | None = None


def typestore() -> Typestore:
    """ROS 2 Jazzy's standard types plus this project's interfaces, registered from their .msg files."""
    global _TYPESTORE
    if _TYPESTORE is None:
        store = get_typestore(Stores.ROS2_JAZZY)
        for package in INTERFACE_PACKAGES:
            dirs = _msg_dirs(package)
            if not dirs:
                raise BagError(f"no .msg files of {package} found (looked in share/{package}/msg and msgs_py)")
            types: dict[str, Any] = {}
            for path in sorted(dirs[0].glob("*.msg")):
                types.update(get_types_from_msg(path.read_text(), f"{package}/msg/{path.stem}"))
            store.register(types)
        _TYPESTORE = store
    return _TYPESTORE


def message_definition(msgtype: str) -> str:
    """The ros2msg text a bag carries for `msgtype`: its fields, then each type it uses (rosbag2's format)."""
    store = typestore()
    if msgtype not in store.fielddefs:
        package, _, name = msgtype.partition("/msg/")
        for folder in _msg_dirs(package):
            path = folder / f"{name}.msg"
            if path.is_file():
                store.register(get_types_from_msg(path.read_text(), msgtype))
                break
    try:
        return store.generate_msgdef(msgtype, ros_version=2)[0]
    except Exception as exc:
        raise BagError(f"no message definition for {msgtype} ({exc})") from None


# ----------------------------------------------------------------------------- QoS as rosbag2 writes it
def qos_entry(
    *, reliable: bool, transient_local: bool, depth: int, keep_all: bool = False, **durations: tuple[int, int]
) -> Qos:
    """One offered QoS profile in rosbags' terms (durations as (sec, nsec); absent: 0, 0)."""

    def time(name: str) -> QosTime:
        sec, nsec = durations.get(name, (0, 0))
        return QosTime(sec, nsec)

    return Qos(
        history=QosHistory.KEEP_ALL if keep_all else QosHistory.KEEP_LAST,
        depth=depth,
        reliability=QosReliability.RELIABLE if reliable else QosReliability.BEST_EFFORT,
        durability=QosDurability.TRANSIENT_LOCAL if transient_local else QosDurability.VOLATILE,
        deadline=time("deadline"),
        lifespan=time("lifespan"),
        liveliness=QosLiveliness.AUTOMATIC,
        liveliness_lease_duration=time("liveliness_lease_duration"),
        avoid_ros_namespace_conventions=False,
    )


def _yaml() -> YAML:
    yaml = YAML(typ="safe")
    yaml.default_flow_style = False
    return yaml


def _dump(data: Any) -> str:
    out = StringIO()
    _yaml().dump(data, out)
    return out.getvalue()


# ----------------------------------------------------------------------------- writing
class _CommitFile:
    """The stream the MCAP writer writes to: it keeps everything in memory until `commit`, which puts it
    in the file with one write at the offset where the previous provisional end began."""

    def __init__(self, path: Path) -> None:
        self.fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o644)
        self.committed = 0  # bytes of records on disk, the provisional end not counted
        self.pending = bytearray()

    def write(self, data: bytes | bytearray | memoryview) -> int:
        self.pending += data
        return len(data)

    def tell(self) -> int:
        return self.committed + len(self.pending)

    def flush(self) -> None:
        """The writer's own flush: nothing reaches the file before `commit`."""

    def commit(self, final: bool = False) -> None:
        data = memoryview(bytes(self.pending) + (b"" if final else PROVISIONAL_END))
        offset = self.committed
        while data:
            written = os.pwrite(self.fd, data, offset)
            data, offset = data[written:], offset + written
        self.committed += len(self.pending)
        self.pending.clear()
        if final:
            os.ftruncate(self.fd, self.committed)

    def close(self) -> None:
        os.close(self.fd)


@dataclass
class TopicInfo:
    """One recorded topic, as metadata.yaml lists it."""

    name: str
    msgtype: str
    qos: list[Qos]
    type_hash: str = ""
    count: int = 0
    channel: int = 0


@dataclass
class BagWriter:
    """Writes one bag folder: `add_topic`, then `write` raw CDR messages; `flush` makes them durable
    against a kill of this process; `close` writes the MCAP summary (indexes and statistics)."""

    folder: Path
    compress: bool = True
    topics: dict[str, TopicInfo] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.folder = Path(self.folder)
        if self.folder.exists() and any(self.folder.iterdir()):
            raise BagError(f"{self.folder} exists and is not empty; a bag is written into a new folder")
        self.folder.mkdir(parents=True, exist_ok=True)
        self.path = self.folder / f"{self.folder.name}_0.mcap"
        self._file = _CommitFile(self.path)
        self._writer = Writer(
            cast(Any, self._file),
            chunk_size=4 * 2**20,
            compression=CompressionType.ZSTD if self.compress else CompressionType.NONE,
            index_types=IndexType.ALL,
        )
        self._writer.start(profile="ros2", library="npp-record")
        self._schemas: dict[str, int] = {}
        self.start_ns: int | None = None
        self.end_ns = 0
        self.closed = False
        self.flush()

    def add_topic(self, name: str, msgtype: str, qos: list[Qos], type_hash: str = "") -> TopicInfo:
        if name in self.topics:
            raise BagError(f"topic {name} is already in the bag")
        if msgtype not in self._schemas:
            self._schemas[msgtype] = self._writer.register_schema(
                msgtype, "ros2msg", message_definition(msgtype).encode()
            )
        qos_text = _dump(dump_qos_v9(qos)).strip()
        channel = self._writer.register_channel(name, "cdr", self._schemas[msgtype], {"offered_qos_profiles": qos_text})
        info = TopicInfo(name, msgtype, list(qos), type_hash or typestore().hash_rihs01(msgtype), channel=channel)
        self.topics[name] = info
        return info

    def write(self, topic: TopicInfo, data: bytes, log_ns: int, publish_ns: int | None = None) -> None:
        self._writer.add_message(topic.channel, log_ns, bytes(data), publish_ns or log_ns, sequence=topic.count)
        topic.count += 1
        self.start_ns = log_ns if self.start_ns is None else min(self.start_ns, log_ns)
        self.end_ns = max(self.end_ns, log_ns)

    @property
    def message_count(self) -> int:
        return sum(t.count for t in self.topics.values())

    def flush(self) -> None:
        """Every message written so far survives a kill of this process from now on."""
        self._writer.flush()
        self._file.commit()
        self._write_metadata()

    def close(self) -> None:
        if self.closed:
            return
        self._writer.finish()
        self._file.commit(final=True)
        self._file.close()
        self._write_metadata()
        self.closed = True

    def _write_metadata(self) -> None:
        write_metadata(self.folder, self.path.name, list(self.topics.values()), self.start_ns, self.end_ns)


def write_metadata(folder: Path, file_name: str, topics: list[TopicInfo], start_ns: int | None, end_ns: int) -> None:
    """metadata.yaml as rosbag2 (version 9) writes it, replaced atomically."""
    count = sum(t.count for t in topics)
    start = start_ns if start_ns is not None else 0
    duration = max(0, end_ns - start) if start_ns is not None else 0
    info = {
        "version": BAG_VERSION,
        "storage_identifier": "mcap",
        "relative_file_paths": [file_name],
        "duration": {"nanoseconds": duration},
        "starting_time": {"nanoseconds_since_epoch": start},
        "message_count": count,
        "topics_with_message_count": [
            {
                "topic_metadata": {
                    "name": t.name,
                    "type": t.msgtype,
                    "serialization_format": "cdr",
                    "offered_qos_profiles": dump_qos_v9(t.qos),
                    "type_description_hash": t.type_hash,
                },
                "message_count": t.count,
            }
            for t in topics
        ],
        "compression_format": "",
        "compression_mode": "",
        "files": [
            {
                "path": file_name,
                "starting_time": {"nanoseconds_since_epoch": start},
                "duration": {"nanoseconds": duration},
                "message_count": count,
            }
        ],
        "custom_data": None,
        "ros_distro": "jazzy",
    }
    tmp = folder / (METADATA + ".tmp")
    tmp.write_text(_dump({"rosbag2_bagfile_information": info}))
    tmp.replace(folder / METADATA)


# ----------------------------------------------------------------------------- repair
def _mcap_file(folder: Path) -> Path:
    files = sorted(folder.glob("*.mcap"))
    if not files:
        raise BagError(f"{folder} holds no .mcap file: not a bag folder written by npp-record")
    return files[0]


def is_complete(path: Path) -> bool:
    """Whether the MCAP file ends with a footer and the closing magic."""
    size = path.stat().st_size
    if size < 8 + 9 + 37:
        return False
    with path.open("rb") as fh:
        fh.seek(-37, os.SEEK_END)
        tail = fh.read()
    return tail[:9] == struct.pack("<BQ", 0x02, 20) and tail[-8:] == MAGIC


def repair(folder: Path) -> str:
    """Cut a torn MCAP file back to its last complete record, close it, and rewrite metadata.yaml.

    Needed only when a recorder was killed inside a flush's write; returns what was done.
    """
    folder = Path(folder)
    path = _mcap_file(folder)
    if is_complete(path):
        return f"{path} is complete; nothing to repair"
    data = path.read_bytes()
    if not data.startswith(MAGIC):
        raise BagError(f"{path} does not start with the MCAP magic: not an MCAP file")
    pos, good = len(MAGIC), len(MAGIC)
    while pos + 9 <= len(data):
        opcode, length = struct.unpack_from("<BQ", data, pos)
        end = pos + 9 + length
        if end > len(data) or opcode in (0x0F, 0x02):  # torn record, or the old provisional end
            break
        pos = good = end
    with path.open("r+b") as fh:
        fh.truncate(good)
        fh.seek(good)
        fh.write(PROVISIONAL_END)
    cut = len(data) - good
    topics = _scan_topics(folder, path)
    counts = [t.count for t in topics]
    return f"{path}: cut {cut} bytes of a torn write, closed it; {sum(counts)} messages on {len(topics)} topics"


def _scan_topics(folder: Path, path: Path) -> list[TopicInfo]:
    """Rebuild metadata.yaml from what the MCAP file holds."""
    from rosbags.rosbag2.storage_mcap import McapReader  # the storage layer: reads an MCAP without metadata

    reader = McapReader(path)
    reader.open()
    try:
        stats = reader.statistics
        assert stats is not None
        topics = [
            TopicInfo(
                c.topic,
                c.msgtype,
                list(cast(Any, c.ext).offered_qos_profiles),
                typestore().hash_rihs01(c.msgtype) if c.msgtype in typestore().fielddefs else "",
                stats.channel_message_counts.get(c.id, 0),
            )
            for c in reader.connections
        ]
        start = stats.start_time if stats.message_count else None
        write_metadata(folder, path.name, topics, start, stats.end_time)
    finally:
        reader.close()
    return topics


# ----------------------------------------------------------------------------- reading
@dataclass
class BagMessage:
    topic: str
    msgtype: str
    log_ns: int
    raw: bytes
    qos: list[Qos]
    msg: Any = None  # the message as a rosbags dataclass (same field names as the ROS message), if decoded


def open_reader(folder: Path) -> AnyReader:
    """An opened AnyReader on a bag folder; a refusal says what is wrong and what to do."""
    folder = Path(folder)
    if not (folder / METADATA).is_file():
        raise BagError(f"{folder} is not a bag folder (no {METADATA})")
    path = _mcap_file(folder)
    if not is_complete(path):
        raise BagError(
            f"{path} ends in the middle of a write (its recorder was killed while flushing); "
            f"`npp-record --repair {folder}` keeps every complete record"
        )
    reader = AnyReader([folder])
    try:
        reader.open()
    except Exception as exc:
        raise BagError(f"cannot read the bag {folder}: {exc}") from None
    return reader


def read_messages(folder: Path, topics: Iterable[str] | None = None, decode: bool = True) -> Iterator[BagMessage]:
    """Messages in log-time order; `topics` keeps those whose name ends with one of these (e.g. 'npp/gap')."""
    suffixes = None if topics is None else tuple("/" + t.strip("/") for t in topics)
    reader = open_reader(folder)
    try:
        connections = [c for c in reader.connections if suffixes is None or c.topic.endswith(suffixes)]
        if not connections:
            return
        for connection, log_ns, raw in reader.messages(connections=connections):
            qos = list(cast(Any, connection.ext).offered_qos_profiles)
            msg = reader.deserialize(raw, connection.msgtype) if decode else None
            yield BagMessage(connection.topic, connection.msgtype, log_ns, bytes(raw), qos, msg)
    finally:
        reader.close()

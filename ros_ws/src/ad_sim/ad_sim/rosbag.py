"""rosbag2-compatible MCAP bags without a ROS runtime: writer, reader, message schemas.

A bag is a folder holding ``metadata.yaml`` (rosbag2 format version 9) and one or more
``<folder>_<i>.mcap`` files (profile ``ros2``, ``ros2msg`` schemas with the complete
dependency definitions, ``cdr`` messages, zstd-compressed chunks), i.e. what
``ros2 bag record -s mcap`` writes on ROS 2 Jazzy, so ``ros2 bag info/play``, rosbags and
Foxglove read it.

Log time of a message is its header stamp (simulated time) for the simulator topics; the
recorder keeps the receive wall time as publish time.

This module never imports rclpy: it runs on the GPU machine and in training.
"""

from __future__ import annotations

import argparse
import bisect
import contextlib
import heapq
import io
import itertools
import json
import mmap
import os
import re
import shutil
import struct
import sys
import warnings
import zlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable, Iterator, NamedTuple

import yaml
from mcap.data_stream import ReadDataStream
from mcap.exceptions import McapError
from mcap.opcode import Opcode
from mcap.records import Channel, Chunk, ChunkIndex, Footer, Message, Schema
from mcap.stream_reader import MAGIC_SIZE, StreamReader, breakup_chunk
from mcap.writer import CompressionType, Writer
from mcap_ros2._dynamic import serialize_dynamic
from mcap_ros2.decoder import DecoderFactory

MCAP_MAGIC = b"\x89MCAP0\r\n"
DEFINITION_DELIMITER = "=" * 80
SCHEMA_DIR = Path(__file__).resolve().parent / "data" / "schemas"
TYPE_HASHES_FILE = "type_hashes.json"
# The message types the simulator publishes; their definitions are vendored in SCHEMA_DIR.
VENDORED_TYPES = (
    "ad_msgs/msg/SimInstance",
    "sensor_msgs/msg/Image",
    "sensor_msgs/msg/CameraInfo",
    "sensor_msgs/msg/PointCloud2",
)
ROS_DISTRO = "jazzy"
METADATA_FILE = "metadata.yaml"
# rmw's "infinite" duration, as rosbag2 (format 9) stores it.
INFINITE_DURATION = {"sec": 9223372036, "nsec": 854775807}
_FOOTER_RECORD_SIZE = 1 + 8 + 8 + 8 + 4
_PRIMITIVE_TYPES = frozenset(
    "bool byte char float32 float64 int8 uint8 int16 uint16 int32 uint32 int64 uint64 string wstring".split()
)
# Field types in a .msg text ("pkg/Type" in "pkg/Type[] name"), as rosbag2 finds them.
_MSG_FIELD_TYPE = re.compile(r"(?:^|\n)\s*([a-zA-Z0-9_/]+)(?:\[[^\]]*\])?\s+")
MIN_SPLIT_SIZE = 64 * 1024  # smallest max_bag_size: a split file holds at least one chunk's worth
MAX_MCAP_TIME = 2**64 - 1  # MCAP times are unsigned 64-bit nanoseconds


class BagError(ValueError):
    """A bag (or one of its files) cannot be read or written as asked."""


class BagDamaged(BagError):
    """Part of a bag is damaged or missing (a killed writer, a corrupt copy, an unusable metadata.yaml);
    recover=True reads the rest. The message names the command-line flag, --recover, as every tool
    that reads bags offers it; a note (shown with a traceback) names the Python equivalent."""

    def __init__(self, message: str):
        super().__init__(message)
        self.add_note("In Python: BagReader(path, recover=True) reads what is readable.")


class BagWriteError(BagError, OSError):
    """Writing a bag's file failed (a full disk, a file system gone read-only, an I/O error): the writer is
    stopped, and its files keep every chunk written before (an OSError too, for callers that catch those)."""


class BagUnreadable(BagError):
    """Recovering found no message at all: every file of the bag is damaged before its first
    complete chunk (or empty)."""


RECOVER_ADVICE = "pass --recover to read what is readable"


# --------------------------------------------------------------------------- schemas


@dataclass(frozen=True)
class MessageSchema:
    """What a bag needs to describe one message type."""

    name: str  # "pkg/msg/Type"
    definition: str  # ros2msg text with every dependency appended
    type_hash: str  # "RIHS01_..." (empty if unknown)


def split_type(type_name: str) -> tuple[str, str, str]:
    """'pkg/msg/Type' (or 'pkg/Type') -> (package, namespace, name)."""
    parts = type_name.split("/")
    if len(parts) == 2:
        return parts[0], "msg", parts[1]
    if len(parts) == 3:
        return parts[0], parts[1], parts[2]
    raise BagError(f"message type {type_name!r} is not of the form pkg/msg/Type")


def ament_prefixes() -> list[Path]:
    """Install prefixes to search for interface files: AMENT_PREFIX_PATH, then the venv."""
    prefixes = [Path(p) for p in os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep) if p]
    prefixes.append(Path(sys.prefix))
    return prefixes


def _interface_file(type_name: str, suffix: str, prefixes: Iterable[Path]) -> Path:
    package, namespace, name = split_type(type_name)
    searched = []
    for prefix in prefixes:
        candidate = Path(prefix) / "share" / package / namespace / f"{name}{suffix}"
        if candidate.is_file():
            return candidate
        searched.append(str(candidate))
    raise BagError(
        f"no {suffix} file for {type_name}; looked in: {', '.join(searched)}. "
        "Source the workspace (ros_ws/install/setup.bash) so AMENT_PREFIX_PATH names it."
    )


def build_message_definition(type_name: str, prefixes: Iterable[Path] | None = None) -> str:
    """The complete ros2msg definition of `type_name`, built exactly as rosbag2 builds it.

    The type's .msg text comes first; each dependency follows once, depth first in sorted
    order, after a line of 80 '=' and a line "MSG: pkg/Type".
    """
    prefixes = list(ament_prefixes() if prefixes is None else prefixes)
    seen: set[str] = set()

    def append(type_ref: str) -> str:
        package = type_ref.split("/")[0]
        text = _interface_file(type_ref, ".msg", prefixes).read_text()
        dependencies = set()
        for match in _MSG_FIELD_TYPE.finditer(text):
            dep = match.group(1)
            if dep in _PRIMITIVE_TYPES:
                continue
            dependencies.add(dep if "/" in dep else f"{package}/{dep}")
        for dep in sorted(dependencies):
            if dep not in seen:
                seen.add(dep)
                text += f"\n{DEFINITION_DELIMITER}\nMSG: {dep}\n" + append(dep)
        return text

    return append(type_name)


def installed_type_hash(type_name: str, prefixes: Iterable[Path] | None = None) -> str:
    """The RIHS01 hash that rosidl generated for `type_name` (share/<pkg>/msg/<Type>.json)."""
    prefixes = list(ament_prefixes() if prefixes is None else prefixes)
    package, namespace, name = split_type(type_name)
    path = _interface_file(type_name, ".json", prefixes)
    full_name = f"{package}/{namespace}/{name}"
    for entry in json.loads(path.read_text())["type_hashes"]:
        if entry["type_name"] == full_name:
            return entry["hash_string"]
    raise BagError(f"{path} holds no type hash for {full_name}")


def _vendored_file(type_name: str) -> Path:
    package, _, name = split_type(type_name)
    return SCHEMA_DIR / f"{package}__{name}.msg"


def vendor_schemas(out_dir: Path = SCHEMA_DIR, prefixes: Iterable[Path] | None = None) -> list[Path]:
    """Write the vendored definitions and type hashes of VENDORED_TYPES from installed ROS files."""
    prefixes = list(ament_prefixes() if prefixes is None else prefixes)
    out_dir.mkdir(parents=True, exist_ok=True)
    written = []
    hashes = {}
    for type_name in VENDORED_TYPES:
        path = out_dir / _vendored_file(type_name).name
        path.write_text(build_message_definition(type_name, prefixes))
        hashes[type_name] = installed_type_hash(type_name, prefixes)
        written.append(path)
    hashes_path = out_dir / TYPE_HASHES_FILE
    hashes_path.write_text(json.dumps(hashes, indent=2) + "\n")
    return [*written, hashes_path]


def load_schema(type_name: str) -> MessageSchema:
    """Schema of `type_name`: vendored for the simulator types, else from the ROS install."""
    package, namespace, name = split_type(type_name)
    full_name = f"{package}/{namespace}/{name}"
    if full_name in VENDORED_TYPES:
        hashes = json.loads((SCHEMA_DIR / TYPE_HASHES_FILE).read_text())
        return MessageSchema(full_name, _vendored_file(full_name).read_text(), hashes[full_name])
    return MessageSchema(full_name, build_message_definition(full_name), installed_type_hash(full_name))


def starts_with_header(definition: str) -> bool:
    """True if the first field of the (top-level) definition is a std_msgs/Header."""
    for line in definition.splitlines():
        line = line.split("#", 1)[0].strip()
        if line:
            return line.split()[0] in ("std_msgs/Header", "Header")
    return False


def header_stamp_ns(cdr: bytes) -> int:
    """Stamp of a CDR message whose first field is std_msgs/Header (after the 4-byte encapsulation).
    ValueError if it cannot be a log time: MCAP's are unsigned, and a nanosec of 1e9 or more is no time."""
    try:
        sec, nanosec = struct.unpack_from("<iI" if cdr[1] == 1 else ">iI", cdr, 4)
    except (IndexError, struct.error):  # raw bytes from a publisher, not checked against the type
        raise ValueError(f"a message of {len(cdr)} bytes is too short to hold a header stamp") from None
    if sec < 0 or nanosec >= 1_000_000_000:
        raise ValueError(f"header stamp {sec} s {nanosec} ns cannot be a log time (negative, or nanosec >= 1e9)")
    return sec * 1_000_000_000 + nanosec


# --------------------------------------------------------------------------- QoS


def qos_profile(
    reliability: str = "reliable",
    durability: str = "volatile",
    history: str = "keep_last",
    depth: int = 10,
    deadline: dict | None = None,
    lifespan: dict | None = None,
    liveliness: str = "automatic",
    liveliness_lease_duration: dict | None = None,
) -> dict:
    """One offered QoS profile as rosbag2 (format 9) writes it in metadata and channel metadata."""
    return {
        "history": history,
        "depth": int(depth),
        "reliability": reliability,
        "durability": durability,
        "deadline": dict(deadline or INFINITE_DURATION),
        "lifespan": dict(lifespan or INFINITE_DURATION),
        "liveliness": liveliness,
        "liveliness_lease_duration": dict(liveliness_lease_duration or INFINITE_DURATION),
        "avoid_ros_namespace_conventions": False,
    }


def parse_offered_qos_profiles(value: Any) -> list[dict]:
    """A topic's offered_qos_profiles from metadata.yaml: a list of profiles, or the YAML string holding one that
    rosbag2 wrote before format 9; [] if there are none. ValueError with a one-line reason if it is unusable."""
    if isinstance(value, str):
        try:
            value = yaml.safe_load(value)
        except yaml.YAMLError as exc:  # its own message runs over several lines
            raise ValueError(f"not YAML ({getattr(exc, 'problem', None) or type(exc).__name__})") from None
    if not value:
        return []
    if not (isinstance(value, list) and all(isinstance(profile, dict) for profile in value)):
        raise ValueError(f"not a list of profiles ({value!r:.60})")
    return value


def _dump_yaml(data: Any) -> str:
    return yaml.safe_dump(data, sort_keys=False, default_flow_style=False)


# --------------------------------------------------------------------------- writer


class _UnbufferedFile:
    """Write-through file: each record group the MCAP writer emits reaches the OS at once,
    so a killed writer leaves every complete chunk on disk."""

    def __init__(self, path: Path):
        self._file = open(path, "xb", buffering=0)  # noqa: SIM115 (closed in close())
        # Chunk records written whole: the MCAP writer hands each one over alone (it writes out what it holds
        # before a chunk record, and the chunk record before its message indexes).
        self.chunks = 0

    def write(self, data: bytes) -> int:
        """All of `data` or, when writing fails (a full disk), none of it: the part written is cut off
        again, so that the file stays whole records, readable up to there, and what follows is not
        written after half a record."""
        start = self._file.tell()
        view = memoryview(data)
        try:
            while view:
                view = view[self._file.write(view) :]
        except OSError:
            with contextlib.suppress(OSError):  # freeing space works on a full disk
                self._file.truncate(start)
                self._file.seek(start)
            raise
        if len(data) and data[0] == Opcode.CHUNK:
            self.chunks += 1
        return len(data)

    def tell(self) -> int:
        return self._file.tell()

    def flush(self) -> None:
        pass

    def close(self) -> None:
        self._file.close()


@dataclass
class _Topic:
    name: str
    schema: MessageSchema
    qos_profiles: list[dict]
    message_count: int = 0


@dataclass
class _FileStats:
    path: str
    start: int | None = None
    end: int | None = None
    message_count: int = 0

    def add(self, log_time: int) -> None:
        self.start = log_time if self.start is None else min(self.start, log_time)
        self.end = log_time if self.end is None else max(self.end, log_time)
        self.message_count += 1


class BagWriter:
    """Writes a rosbag2 bag folder of MCAP files.

    write() takes CDR bytes (what an rclpy raw subscription delivers) or a dict/object that is
    encoded with the topic's schema (mcap_ros2's encoder). metadata.yaml is written at open,
    at each split and at close; close() must run for the MCAP summaries to be written
    (a killed writer still leaves complete chunks readable, see BagReader(recover=True)).
    A failed write (a full disk, ...) raises BagWriteError and stops the writer, its files left as a
    killed writer's are: every complete chunk readable; `lost` then counts, per topic, the messages
    written to it that were not yet in a complete chunk (they are not in the topic counts).
    max_bag_size (bytes; 0: no split) splits the bag as rosbag2 does: a file is closed once it has reached that size,
    so it exceeds it by up to its last chunk and its summary. Chunks are then at most an eighth of max_bag_size and one
    message (the MCAP writer ends a chunk once it exceeds its size), which keeps that small.
    """

    def __init__(
        self,
        path: str | os.PathLike,
        *,
        max_bag_size: int = 0,
        compression: str = "zstd",
        chunk_size: int = 1024 * 1024,
        custom_data: dict[str, str] | None = None,
    ):
        self.path = Path(path)
        if self.path.exists() and (not self.path.is_dir() or any(self.path.iterdir())):
            raise BagError(f"bag output {self.path} already exists; remove it or choose another path")
        compressions = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4, "none": CompressionType.NONE}
        if compression not in compressions:
            raise BagError(f"unknown compression {compression!r}; use one of {sorted(compressions)}")
        if max_bag_size and max_bag_size < MIN_SPLIT_SIZE:
            raise BagError(f"max_bag_size {max_bag_size} is too small; use 0 (no split) or >= {MIN_SPLIT_SIZE} bytes")
        self.path.mkdir(parents=True, exist_ok=True)
        self.max_bag_size = int(max_bag_size)
        self.chunk_size = min(int(chunk_size), self.max_bag_size // 8) if self.max_bag_size else int(chunk_size)
        self._compression = compressions[compression]
        self.custom_data = dict(custom_data or {})
        self._topics: dict[str, _Topic] = {}
        self._encoders: dict[str, Any] = {}
        self._files: list[_FileStats] = []
        self._stream: _UnbufferedFile | None = None
        self._mcap: Writer | None = None
        self._channel_ids: dict[str, int] = {}
        self._schema_ids: dict[str, int] = {}
        self._closed = False
        self._error = ""  # why writing stopped (BagWriteError), after a failed write
        self._unreported = False  # the failure was not raised yet
        self._pending: dict[str, int] = {}  # topic -> messages of the current file not yet in a written chunk
        self._chunks_seen = 0  # the stream's chunk count when _pending was last settled (_settle)
        self.lost: dict[str, int] = {}  # topic -> messages lost by a failed write (not in the counts)
        try:
            self._open_next_file()
        except OSError as exc:  # a full disk: its error names no file
            exc.filename = exc.filename or str(self.path / self._files[-1].path if self._files else self.path)
            raise

    # -- topics and messages

    @property
    def message_count(self) -> int:
        return sum(t.message_count for t in self._topics.values())

    def has_topic(self, topic: str) -> bool:
        return topic in self._topics

    def add_topic(
        self,
        topic: str,
        type_name: str,
        qos_profiles: list[dict] | None = None,
        schema: MessageSchema | None = None,
    ) -> None:
        """Declare a topic before writing to it (type "pkg/msg/Type", offered QoS profiles)."""
        if topic in self._topics:
            return
        schema = schema or load_schema(type_name)
        with self._writing():
            self._topics[topic] = _Topic(topic, schema, list(qos_profiles or [qos_profile()]))
            self._register_channel(self._topics[topic])
            self._write_metadata()

    def write(self, topic: str, log_time_ns: int, message: bytes | Any, publish_time_ns: int | None = None) -> None:
        """Write one message: CDR bytes, or a dict/object encoded with the topic's schema."""
        if self._closed:
            raise BagError(f"bag {self.path} is closed")
        info = self._topics.get(topic)
        if info is None:
            raise BagError(f"topic {topic} was not added to bag {self.path}; call add_topic() first")
        log_time_ns = int(log_time_ns)
        publish_time_ns = log_time_ns if publish_time_ns is None else int(publish_time_ns)
        # Checked first: the MCAP writer keeps a time in its statistics before it fails on it, and fails again at close.
        if not (0 <= log_time_ns <= MAX_MCAP_TIME and 0 <= publish_time_ns <= MAX_MCAP_TIME):
            raise BagError(f"log time {log_time_ns} ns or publish time {publish_time_ns} ns of a message on {topic} is "
                           f"not an MCAP time (0 to {MAX_MCAP_TIME} ns)")
        if not isinstance(message, (bytes, bytearray, memoryview)):
            message = self._encode(info.schema, message)
        try:
            with self._writing():
                self._settle()  # (a chunk written since the last message, by a topic's channel, say)
                # Counted before it is written: a failure after its chunk was written (at the message indexes,
                # at a split's summary) leaves it in the file, a failure before that among the lost (_fail).
                sequence = info.message_count
                info.message_count += 1
                self._files[-1].add(log_time_ns)
                self._pending[topic] = self._pending.get(topic, 0) + 1
                self._mcap.add_message(
                    channel_id=self._channel_ids[topic],
                    log_time=log_time_ns,
                    data=bytes(message),
                    publish_time=publish_time_ns,
                    sequence=sequence,
                )
                self._settle()
                if self.max_bag_size and self._stream.tell() >= self.max_bag_size:
                    self._close_file()
                    self._open_next_file()
        except BagWriteError as exc:
            if exc.__cause__ is None:  # writing had stopped before: nothing was counted
                raise
            if self.lost.get(topic):  # this message was lost with the chunk in progress: its write fails
                self.lost[topic] -= 1
                raise
            self._unreported = True  # it is in a complete chunk: the next write (or close) says why it stopped

    def flush(self) -> None:
        """Close the chunk in progress so that it survives a kill of this process."""
        if self._mcap is not None and not self._closed:
            with self._writing():
                self._mcap.flush()  # (its chunk written, the pending messages are settled at the next _settle)

    def close(self) -> None:
        """Finish the file in progress and metadata.yaml; after a failed write, only mark the writer closed."""
        if self._closed:
            return
        try:
            if not self._error or self._unreported:
                with self._writing():
                    self._close_file()
                    self._write_metadata()
        finally:
            self._closed = True

    def __enter__(self) -> BagWriter:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    # -- internals

    @contextlib.contextmanager
    def _writing(self):
        """Around whatever writes the bag's files: after an OSError the MCAP writer's state is unknown (its chunk in
        progress gone), so writing stops there, with a BagWriteError now and at each later write."""
        if self._error:
            self._unreported = False
            raise BagWriteError(self._error)
        try:
            yield
        except OSError as exc:
            raise self._fail(exc) from exc

    def _settle(self) -> None:
        """The pending messages are all in the chunk in progress: once the stream has written a chunk since they
        were counted, they are in the file."""
        if self._stream.chunks != self._chunks_seen:
            self._pending.clear()
            self._chunks_seen = self._stream.chunks

    def _fail(self, exc: OSError) -> BagWriteError:
        current = self.path / self._files[-1].path
        self._settle()
        for topic, count in self._pending.items():  # the counts say what the files hold
            self._topics[topic].message_count -= count
        self._files[-1].message_count -= sum(self._pending.values())
        self.lost, self._pending = self._pending, {}
        lost = sum(self.lost.values())
        self._error = (
            f"cannot write {exc.filename or current}: {exc.strerror or exc}. Writing stopped; the bag's files keep "
            "every chunk written before" + (f" (not the last {lost} messages, in no complete chunk yet)" if lost else "")
            + f": read them with --recover, or make a complete bag of them with `python -m ad_sim.rosbag repair "
            f"{self.path} --out NEW`. Free space on that file system, or write to another folder"
        )
        with contextlib.suppress(OSError):
            self._stream.close()  # ends after its last whole record (_UnbufferedFile)
        self._mcap = None
        with contextlib.suppress(OSError):  # the true counts, if there is room for them
            self._write_metadata()
        return BagWriteError(self._error)

    def _encode(self, schema: MessageSchema, message: Any) -> bytes:
        encoder = self._encoders.get(schema.name)
        if encoder is None:
            encoder = serialize_dynamic(schema.name, schema.definition)[schema.name]
            self._encoders[schema.name] = encoder
        return encoder(message)

    def _open_next_file(self) -> None:
        name = f"{self.path.name}_{len(self._files)}.mcap"
        self._stream = _UnbufferedFile(self.path / name)
        self._chunks_seen = 0
        self._files.append(_FileStats(name))
        self._mcap = Writer(self._stream, chunk_size=self.chunk_size, compression=self._compression)
        self._mcap.start(profile="ros2", library="ad_sim.rosbag")
        self._channel_ids.clear()
        self._schema_ids.clear()
        for info in self._topics.values():
            self._register_channel(info)
        self._write_metadata()

    def _register_channel(self, info: _Topic) -> None:
        schema_id = self._schema_ids.get(info.schema.name)
        if schema_id is None:
            schema_id = self._mcap.register_schema(info.schema.name, "ros2msg", info.schema.definition.encode())
            self._schema_ids[info.schema.name] = schema_id
        self._channel_ids[info.name] = self._mcap.register_channel(
            topic=info.name,
            message_encoding="cdr",
            schema_id=schema_id,
            metadata={
                "offered_qos_profiles": _dump_yaml(info.qos_profiles),
                "topic_type_hash": info.schema.type_hash,
            },
        )

    def _close_file(self) -> None:
        # rosbag2 stores the bag metadata in every file it closes, under the name "rosbag2".
        self._mcap.add_metadata("rosbag2", {"serialized_metadata": _dump_yaml(self._metadata())})
        self._mcap.finish()
        self._stream.close()
        self._mcap = None
        self._pending.clear()

    def _metadata(self) -> dict:
        starts = [f.start for f in self._files if f.start is not None]
        ends = [f.end for f in self._files if f.end is not None]
        start = min(starts, default=0)
        return {
            "version": 9,
            "storage_identifier": "mcap",
            "duration": {"nanoseconds": max(ends, default=0) - start},
            "starting_time": {"nanoseconds_since_epoch": start},
            "message_count": self.message_count,
            "topics_with_message_count": [
                {
                    "topic_metadata": {
                        "name": t.name,
                        "type": t.schema.name,
                        "serialization_format": "cdr",
                        "offered_qos_profiles": t.qos_profiles,
                        "type_description_hash": t.schema.type_hash,
                    },
                    "message_count": t.message_count,
                }
                for t in self._topics.values()
            ],
            "compression_format": "",
            "compression_mode": "",
            "relative_file_paths": [f.path for f in self._files],
            "files": [
                {
                    "path": f.path,
                    "starting_time": {"nanoseconds_since_epoch": f.start or 0},
                    "duration": {"nanoseconds": (f.end or 0) - (f.start or 0)},
                    "message_count": f.message_count,
                }
                for f in self._files
            ],
            "custom_data": dict(self.custom_data),
            "ros_distro": ROS_DISTRO,
        }

    def _write_metadata(self) -> None:
        target = self.path / METADATA_FILE
        tmp = target.with_suffix(".yaml.tmp")
        try:
            tmp.write_text(_dump_yaml({"rosbag2_bagfile_information": self._metadata()}))
            tmp.replace(target)
        except OSError:  # a full disk: no half-written file left beside the bag (metadata.yaml stays as it was)
            tmp.unlink(missing_ok=True)
            raise


# --------------------------------------------------------------------------- reader


class BagMessage(NamedTuple):
    topic: str
    log_time_ns: int
    message: Any  # decoded object (attributes as in the .msg), or CDR bytes if raw


@dataclass
class _FileScan:
    """State of reading one .mcap file, kept by its BagReader from one pass over the files to the next."""

    path: Path
    schemas: dict[int, Schema] = field(default_factory=dict)
    channels: dict[int, Channel] = field(default_factory=dict)
    decoders: dict[int, Any] = field(default_factory=dict)  # by channel id, built on first use
    truncated: str = ""  # what a killed writer left, when recovering: said once the file is scanned
    damage: str = ""  # when recovering: how the file is damaged, said if nothing is readable in the bag
    messages: int | None = None  # messages read, once the file's records are scanned
    recovered: str = ""  # when recovering a truncated file: what was recovered and lost, said after the scan
    # Without a summary: the earliest log time of each data-section record holding messages, by offset, once walked
    starts: dict[int, int] | None = None
    # The file's size when the above was learnt: a file that has grown since (a recorder still writing, or closing it
    # with its summary) is learnt anew (BagReader._begin_pass)
    size: int | None = None


_RECORD_TYPES = {Opcode.SCHEMA: Schema, Opcode.CHANNEL: Channel}


@contextlib.contextmanager
def _mapped(path: Path):
    """The file's bytes, memory-mapped (bags can be larger than memory)."""
    try:
        with open(path, "rb") as file:
            if os.fstat(file.fileno()).st_size == 0:
                yield b""
                return
            with mmap.mmap(file.fileno(), 0, access=mmap.ACCESS_READ) as data:
                yield data
    except OSError as exc:
        raise BagError(f"cannot read {path}: {exc}") from exc


def read_metadata(path: Path) -> dict:
    """The rosbag2_bagfile_information of a metadata.yaml, checked for what readers of it use (the
    file list; each topic's name, type and count); ValueError with a short reason if it is unusable."""
    try:
        text = path.read_text()
    except UnicodeDecodeError:
        raise ValueError("not text") from None
    except OSError as exc:
        raise ValueError(f"cannot read it: {exc.strerror or exc}") from None
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as exc:  # the parser's own message runs over several lines
        problem = getattr(exc, "problem", None) or str(exc).splitlines()[0]
        mark = getattr(exc, "problem_mark", None)
        raise ValueError(f"not YAML: {problem}{f' at line {mark.line + 1}' if mark else ''}") from None
    if data is None:
        raise ValueError("empty")
    info = data.get("rosbag2_bagfile_information") if isinstance(data, dict) else None
    if not isinstance(info, dict):
        raise ValueError("no rosbag2_bagfile_information mapping" if isinstance(data, dict) else
                         f"a YAML {'list' if isinstance(data, list) else 'scalar'}, not rosbag2 metadata")
    files = info.get("relative_file_paths")
    if not isinstance(files, list) or not all(isinstance(f, str) and f for f in files):
        raise ValueError("relative_file_paths is not a list of file names")
    topics = info.get("topics_with_message_count", [])
    if not isinstance(topics, list) or not all(
            isinstance(t, dict) and isinstance(t.get("topic_metadata"), dict)
            and isinstance(t["topic_metadata"].get("name"), str) and isinstance(t["topic_metadata"].get("type"), str)
            and isinstance(t.get("message_count"), int) for t in topics):
        raise ValueError("topics_with_message_count is not a list of topics with a name, type and message_count")
    return info


def _natural_key(path: Path) -> list:
    return [int(part) if part.isdigit() else part for part in re.split(r"(\d+)", path.name)]


class _Undecodable(Exception):
    """One message's bytes do not decode with its topic's schema (BagReader decides what that costs)."""


class BagReader:
    """Iterates (topic, log_time_ns, message) over a bag folder or a single .mcap file,
    in log-time order (ties in file order), decoding with mcap_ros2 (no ROS runtime).

    recover=True reads what a killed writer left: files without a summary are read up to
    the last complete chunk, and corrupt chunks are skipped, each with a warning that says
    what was recovered or lost; a metadata.yaml that is unusable (not rosbag2 metadata, or naming
    missing files) is passed over with a warning, and the .mcap files beside it are read, as when
    it is missing. If that leaves no message at all, reading (or topics()) raises BagUnreadable.
    A summary whose chunk indexes start later than their chunks' messages (a writer's error) is an error
    naming --recover, where it would break the order of the messages read (those of the topics asked for: other topics'
    messages are neither checked nor decoded); recovering reads those messages late, with a warning.
    raw=True yields the CDR bytes instead of decoded messages.
    `problems` lists the reader's warnings, each once however often the files are scanned. What a walk over a file
    without a summary learns (its topics, its chunks' start times) is kept: topics() then reading walks it twice. It is
    kept while the file keeps its size: one that grows meanwhile (a recorder still writing) is walked anew.
    """

    def __init__(
        self,
        path: str | os.PathLike,
        *,
        topics: Iterable[str] | None = None,
        recover: bool = False,
        raw: bool = False,
    ):
        self.path = Path(path)
        self.recover = recover
        self.raw = raw
        self.topic_filter = None if topics is None else set(topics)
        self.metadata: dict | None = None
        self.problems: list[str] = []
        self.files = self._find_files()
        self._scans = [_FileScan(path) for path in self.files]
        self._decoder_factory = DecoderFactory()

    def _find_files(self) -> list[Path]:
        if not self.path.exists():
            raise BagError(f"bag {self.path} does not exist")
        if self.path.is_file():
            if self.path.suffix != ".mcap":
                raise BagError(f"{self.path} is not a .mcap file or a bag folder")
            return [self.path]
        found = sorted(self.path.glob("*.mcap"), key=_natural_key)
        metadata_path = self.path / METADATA_FILE
        files = found
        if not metadata_path.exists():
            if found:
                self._warn(
                    f"bag {self.path} has no metadata.yaml (was the writer killed?); "
                    f"reading the {len(found)} .mcap file(s) found"
                )
        else:
            try:
                metadata = read_metadata(metadata_path)
            except ValueError as exc:
                self._unusable_metadata(f"{metadata_path} is unreadable ({exc})", found)
            else:
                # Kept even when files are missing: their topics' types and QoS are still right.
                self.metadata = metadata
                listed = [self.path / p for p in metadata["relative_file_paths"]]
                # One file by two names ("a.mcap" twice, "../bag/a.mcap") would be read twice.
                real = [os.path.realpath(p) for p in listed]
                twice = sorted({Path(r).name for i, r in enumerate(real) if r in real[:i]})
                if missing := [p.name for p in listed if not p.is_file()]:
                    self._unusable_metadata(f"{metadata_path} names files that are missing: {', '.join(missing)}",
                                            found)
                elif twice:
                    self._unusable_metadata(f"{metadata_path} names {', '.join(twice)} more than once", found)
                else:
                    if extra := [p for p in found if os.path.realpath(p) not in real]:
                        self._warn(f"bag {self.path}: reading .mcap files not named in metadata.yaml: "
                                   f"{', '.join(p.name for p in extra)}")
                    files = listed + extra
        if not files:
            inside = sorted({str(p.parent.relative_to(self.path)) for p in self.path.rglob("*.mcap")})
            hint = f"; the bags in it: {', '.join(inside[:5])}{', ...' if len(inside) > 5 else ''} (pass one)" if inside else ""
            raise BagError(f"bag folder {self.path} holds no .mcap file{hint}")
        return files

    def _unusable_metadata(self, problem: str, found: list[Path]) -> None:
        """metadata.yaml cannot be used: an error naming --recover, or when recovering a warning,
        and the .mcap files `found` beside it are read, as when it is missing."""
        if not found:
            raise BagError(f"{problem}, and no .mcap file lies beside it")
        if not self.recover:
            raise BagDamaged(f"{problem}; pass --recover to read the {len(found)} .mcap file(s) beside it")
        self._warn(f"{problem}; reading the {len(found)} .mcap file(s) beside it")

    def topics(self) -> dict[str, str]:
        """topic -> message type over all files (from the summaries; files without one are scanned)."""
        result = {}
        for scan in self._scans:
            with _mapped(scan.path) as data:
                self._begin_pass(scan, data)
                summary = self._read_summary(scan, data)
                if summary is None:
                    self._record_starts(scan, data)  # the walk that reading takes first, made once
                elif not scan.channels:
                    for _ in self._scan_records(scan, data, summary):
                        pass
            for channel in scan.channels.values():
                schema = scan.schemas.get(channel.schema_id)
                result[channel.topic] = schema.name if schema else ""
        self._scanned()
        return result

    def __iter__(self) -> Iterator[BagMessage]:
        streams = [self._iter_file(i, scan) for i, scan in enumerate(self._scans)]
        for log_time, _, topic, message in heapq.merge(*streams, key=lambda item: (item[0], item[1])):
            yield BagMessage(topic, log_time, message)
        self._scanned()

    def _scanned(self) -> None:
        """After a pass over the files: BagUnreadable if recovering found no message in any of them
        and damage in some (files only read through their summary count as readable); otherwise
        the warnings of what was recovered from each truncated file."""
        scans = self._scans
        if all(scan.messages == 0 for scan in scans) and (damaged := [scan for scan in scans if scan.damage]):
            if len(scans) == 1:
                raise BagUnreadable(f"nothing readable in {scans[0].path}: it {scans[0].damage}")
            raise BagUnreadable(f"nothing readable in {self.path}: "
                                + "; ".join(f"{scan.path} {scan.damage}" for scan in damaged))
        for scan in scans:
            if scan.recovered:
                self._warn(scan.recovered)

    # -- one file

    def _iter_file(self, file_index: int, scan: _FileScan) -> Iterator[tuple[int, tuple[int, int], str, Any]]:
        for log_time, order, channel, data in self._scan_file(scan):  # of the topics asked for only
            if self.raw:
                message = data
            else:
                try:
                    message = self._decode(scan, channel, data)
                except _Undecodable as exc:  # one bad message, not a bad bag: --recover skips just it
                    where = f"{scan.path}: the message on {channel.topic} logged at {log_time / 1e9:.3f} s"
                    if not self.recover:
                        raise BagDamaged(f"{where} does not decode ({exc}). To skip it and report it, "
                                         f"{RECOVER_ADVICE}") from exc
                    self._warn(f"{where} does not decode ({exc}); it was skipped")
                    continue
            yield log_time, (file_index, order), channel.topic, message

    def _decode(self, scan: _FileScan, channel: Channel, data: bytes) -> Any:
        decoder = scan.decoders.get(channel.id)
        if decoder is None:
            schema = scan.schemas.get(channel.schema_id)
            if schema is None:
                raise BagError(f"{scan.path}: topic {channel.topic} has no schema (id {channel.schema_id}); cannot decode it")
            if schema.encoding != "ros2msg" or channel.message_encoding != "cdr":
                raise BagError(
                    f"{scan.path}: topic {channel.topic} uses schema encoding {schema.encoding!r} and message "
                    f"encoding {channel.message_encoding!r}; only ros2msg/cdr can be decoded"
                )
            try:
                decoder = self._decoder_factory.decoder_for(channel.message_encoding, schema)
            except Exception as exc:  # mcap_ros2 raises assorted parse errors
                raise BagError(f"{scan.path}: cannot parse the schema {schema.name} of topic {channel.topic}: {exc}") from exc
            scan.decoders[channel.id] = decoder
        try:
            return decoder(data)
        except Exception as exc:
            raise _Undecodable(f"as {scan.schemas[channel.schema_id].name}: {exc}") from exc

    def _warn(self, message: str) -> None:
        # topics() and iteration scan a summary-less file alike: one warning per problem.
        if message not in self.problems:
            self.problems.append(message)
            warnings.warn(message, stacklevel=3)

    def _problem(self, scan: _FileScan, message: str, recovery: str) -> None:
        """A damaged part of a file: an error saying what --recover would do, or when recovering a
        warning ending in what was done about it."""
        if not self.recover:
            raise BagDamaged(f"{message}. To skip the damaged part and report it, {RECOVER_ADVICE}")
        self._warn(f"{message}; {recovery}")
        scan.damage = scan.damage or "is damaged before its first complete chunk"

    def _truncated(self, scan: _FileScan, what: str, to_recover: str, damage: str) -> None:
        """A file a killed writer left (`what`: "is empty (...)"): an error saying what --recover
        would do, or when recovering noted for the warning after its scan (what was recovered),
        and `damage` for the error if nothing is readable."""
        if not self.recover:
            raise BagDamaged(f"{scan.path} {what}. {to_recover} with --recover")
        scan.truncated = what
        scan.damage = damage

    def _read_summary(self, scan: _FileScan, data) -> list[ChunkIndex] | None:
        """Chunk indexes (and the schemas and channels into `scan`) from the file's summary.

        A file that does not start with the MCAP magic is an error even when recovering. None if the
        file has no footer (a killed writer: an error unless recovering) or no summary."""
        size = len(data)
        start = bytes(data[:MAGIC_SIZE])
        if start != MCAP_MAGIC:
            if not MCAP_MAGIC.startswith(start):
                raise BagError(f"{scan.path} is not an MCAP file (starts with {start!r})")
            # Nothing or part of the magic: the writer was killed as it created the file.
            what = ("is empty (was the writer killed?)" if size == 0
                    else f"is truncated inside the MCAP magic ({size} bytes; was the writer killed?)")
            self._truncated(scan, what, "Read the bag without it", what)
            return None
        footer_at = size - MAGIC_SIZE - _FOOTER_RECORD_SIZE
        if size < 2 * MAGIC_SIZE + _FOOTER_RECORD_SIZE or data[-MAGIC_SIZE:] != MCAP_MAGIC or data[footer_at] != Opcode.FOOTER:
            self._truncated(scan, f"is truncated: no MCAP footer ({size} bytes; was the writer killed?)",
                            "Read every complete chunk of it",
                            f"is truncated before its first complete chunk ({size} bytes; was the writer killed?)")
            return None
        footer = Footer.read(ReadDataStream(io.BytesIO(data[footer_at + 9 : size - MAGIC_SIZE])))
        if footer.summary_start == 0:
            return None
        if not MAGIC_SIZE <= footer.summary_start < footer_at:  # a damaged footer points anywhere
            self._problem(scan, f"{scan.path}: corrupt footer: its summary section starts at byte "
                                f"{footer.summary_start}, outside the file's {size} bytes before the footer",
                          "reading the data section instead")
            return None
        # The footer's CRC covers the summary section and the footer's fields before it: a damaged summary (names of
        # topics and types, where the chunks are) is not to be trusted, and the data section holds all of it again.
        if footer.summary_crc and footer.summary_crc != zlib.crc32(data[footer_at : footer_at + 25],
                                                                   zlib.crc32(data[footer.summary_start : footer_at])):
            self._problem(scan, f"{scan.path}: corrupt summary section at byte {footer.summary_start} (its CRC does "
                                "not match)", "reading the data section instead")
            return None
        chunk_indexes, schemas, channels = [], {}, {}
        try:
            for record in StreamReader(io.BytesIO(data[footer.summary_start :]), skip_magic=True).records:
                if isinstance(record, ChunkIndex):
                    chunk_indexes.append(record)
                elif isinstance(record, Schema):
                    schemas[record.id] = record
                elif isinstance(record, Channel):
                    channels[record.id] = record
            end = MAGIC_SIZE  # chunks lie in the data section, one after another
            for chunk_index in sorted(chunk_indexes, key=lambda c: c.chunk_start_offset):
                if chunk_index.chunk_start_offset < end or chunk_index.chunk_length < 9:
                    raise ValueError(f"a chunk index points at byte {chunk_index.chunk_start_offset}, inside "
                                     "another record")
                end = chunk_index.chunk_start_offset + chunk_index.chunk_length
            if end > footer.summary_start:
                raise ValueError(f"a chunk index points past the data section (to byte {end})")
        except (McapError, struct.error, ValueError) as exc:  # nothing of a damaged summary is used
            self._problem(scan, f"{scan.path}: corrupt summary section at byte {footer.summary_start}: "
                                f"{exc or type(exc).__name__}", "reading the data section instead")
            return None
        scan.schemas.update(schemas)
        scan.channels.update(channels)
        return chunk_indexes

    def _scan_file(self, scan: _FileScan) -> Iterator[tuple[int, int, Channel, bytes]]:
        """Messages of one file as (log_time, order, channel, data), in log-time order."""
        with _mapped(scan.path) as data:
            self._begin_pass(scan, data)
            yield from self._scan_data(scan, data, self._read_summary(scan, data))

    @staticmethod
    def _begin_pass(scan: _FileScan, data) -> None:
        """A pass over the file (`data`, as mapped for it): what earlier passes learnt of it (its records' start
        times, schemas and channels, its damage and what was recovered) is kept only while the file keeps its size.
        A recorder still writing appends chunks that the kept start times know nothing of (their messages came out of
        log-time order), and closing the file adds its summary (it was still said to be truncated)."""
        if scan.size != len(data):
            vars(scan).update(vars(_FileScan(scan.path, size=len(data))))

    def _scan_data(self, scan: _FileScan, data, chunk_indexes: list[ChunkIndex] | None
                   ) -> Iterator[tuple[int, int, Channel, bytes]]:
        """Messages of the data section on the topics asked for (`topic_filter`) as (log_time, order, channel, data), in
        log-time order (ties in file order). The other topics' messages are dropped as each record is read: they are
        neither held nor decoded, and the order check below (a chunk index that starts too late) concerns only the
        messages read, as their order is all that the caller sees.

        Each message is held only until no record after it can hold an earlier one, so that a file is not held in
        memory whole (a killed recorder's can be larger than memory): that takes each record's earliest log time, from
        the summary's chunk indexes (under its CRC) or, without a summary, from the messages themselves
        (_record_starts)."""
        starts = (self._record_starts(scan, data) if chunk_indexes is None
                  else {c.chunk_start_offset: c.message_start_time for c in chunk_indexes})
        offsets = sorted(starts)
        # earliest log time in the record at offsets[i] and every later one: once past offsets[i - 1], messages up to
        # it are released in order.
        release_at = list(itertools.accumulate((starts[o] for o in reversed(offsets)), min))[::-1]
        pending: list[tuple[int, int, Channel, bytes]] = []
        order = 0
        released = None  # log time of the last message released
        wanted = self.topic_filter
        for pos, _, messages in self._scan_records(scan, data, chunk_indexes):
            if wanted is not None:
                messages = [(m, channel) for m, channel in messages if channel.topic in wanted]
            # Only a summary's chunk index can start too late (a writer's error): without one, starts are the messages'.
            if early := [m.log_time for m, _ in messages if released is not None and m.log_time < released]:
                cause = (f"its chunk index says its messages start at {starts[pos]} ns" if pos in starts
                         else "the summary's chunk indexes do not list it")
                where = (f"{scan.path}: the record at byte {pos} holds {len(early)} message(s) logged from {min(early)} "
                         f"ns, before messages read already (up to {released} ns): {cause}")
                if not self.recover:
                    raise BagDamaged(f"{where}. To read such messages late and report them, {RECOVER_ADVICE}")
                self._warn(f"{where}; read late, out of log-time order")
            for message, channel in messages:
                heapq.heappush(pending, (message.log_time, order, channel, message.data))
                order += 1
            following = bisect.bisect_right(offsets, pos)
            while pending and following < len(offsets) and pending[0][0] <= release_at[following]:
                released = pending[0][0]
                yield heapq.heappop(pending)
        while pending:
            yield heapq.heappop(pending)

    def _record_starts(self, scan: _FileScan, data) -> dict[int, int]:
        """A file without a summary: the earliest log time of each data-section record holding messages, by offset,
        from the messages themselves in a walk over its records, one record at a time. A chunk's header says it too,
        but no CRC covers it: a damaged one released messages out of order. Kept in `scan`: topics() walks the file
        as reading does first, and each walk decompresses all of it."""
        if scan.starts is None:
            starts = {}
            for pos, header, messages in self._scan_records(scan, data, None):
                if messages:
                    logged = (min(m.log_time for m, _ in messages), max(m.log_time for m, _ in messages))
                    starts[pos] = logged[0]
                    if header is not None and (logged[0] < header[0] or logged[1] > header[1]):
                        self._warn(f"{scan.path}: damaged chunk header at byte {pos}: it gives log times {header[0]} "
                                   f"to {header[1]} ns, its messages were logged from {logged[0]} to {logged[1]} ns; "
                                   "read in log-time order by their own times")
            scan.starts = starts
        return scan.starts

    def _scan_records(self, scan: _FileScan, data, chunk_indexes: list[ChunkIndex] | None
                      ) -> Iterator[tuple[int, tuple[int, int] | None, list[tuple[Message, Channel]]]]:
        """The data section record by record: (offset, a chunk's (message_start_time, message_end_time) from its
        header or None, the record's messages with their channels); its schemas and channels go into `scan`, and once
        read to its end, the count of its messages and what a truncated file recovered.

        `chunk_indexes` (from a summary that passed its CRC): each is checked to hold a chunk record of its length, and
        a damaged record header cannot hide the chunks after it: reading goes on at the next chunk the summary lists
        (without it, a damaged header ends what can be read, as a cut does)."""
        chunk_lengths = {c.chunk_start_offset: c.chunk_length for c in chunk_indexes or []}
        listed = sorted(chunk_lengths)
        count = 0
        pos = MAGIC_SIZE
        size = len(data)
        cut_at = None  # where the incomplete last record of a recovered file starts

        def header(opcode: int | None, length: int) -> str:
            return "an incomplete record header" if opcode is None else f"opcode 0x{opcode:02x}, {9 + length} bytes"

        while pos < size:
            complete = pos + 9 <= size
            opcode, length = (data[pos], struct.unpack_from("<Q", data, pos + 1)[0]) if complete else (None, 0)
            if chunk_lengths and (expected := chunk_lengths.get(pos)) is not None:
                if opcode != Opcode.CHUNK or 9 + length != expected:
                    self._problem(scan, f"{scan.path}: corrupt record at byte {pos}: the summary lists a chunk of "
                                        f"{expected} bytes there, the record's header says {header(opcode, length)}",
                                  "skipped it and the messages in it")
                    pos += expected
                    continue
            elif (following := bisect.bisect_right(listed, pos)) < len(listed) and (
                    not complete or pos + 9 + length > listed[following] or opcode in (Opcode.DATA_END, Opcode.FOOTER)):
                # A record before a chunk that the summary lists cannot run into it, nor end the data section.
                self._problem(scan, f"{scan.path}: corrupt record at byte {pos} ({header(opcode, length)}): the "
                                    f"summary lists a chunk at byte {listed[following]}",
                              "skipped to that chunk, losing what lay between")
                pos = listed[following]
                continue
            if pos + 9 > size:
                if not self.recover:
                    raise BagDamaged(f"{scan.path} is truncated at byte {pos} (incomplete record header); {RECOVER_ADVICE}")
                cut_at = pos
                break
            end = pos + 9 + length
            if end > size:
                if not self.recover:
                    raise BagDamaged(
                        f"{scan.path} is truncated or corrupt at byte {pos}: a record (opcode 0x{opcode:02x}) of "
                        f"{length} bytes runs past the end of the file ({size} bytes); {RECOVER_ADVICE}"
                    )
                cut_at = pos
                break
            times = None
            try:
                if opcode == Opcode.CHUNK:
                    chunk = Chunk.read(ReadDataStream(io.BytesIO(data[pos + 9 : end])))
                    times = (chunk.message_start_time, chunk.message_end_time)
                    records = breakup_chunk(chunk, validate_crc=True)
                elif opcode in (Opcode.SCHEMA, Opcode.CHANNEL, Opcode.MESSAGE):
                    stream = ReadDataStream(io.BytesIO(data[pos + 9 : end]))
                    records = [Message.read(stream, length) if opcode == Opcode.MESSAGE else _RECORD_TYPES[opcode].read(stream)]
                elif opcode in (Opcode.DATA_END, Opcode.FOOTER):
                    break
                else:
                    records = []
            except Exception as exc:  # decompression, CRC and parse failures of this record
                self._problem(
                    scan, f"{scan.path}: corrupt record (opcode 0x{opcode:02x}) at byte {pos}: {type(exc).__name__}: {exc}",
                    "skipped it and the messages in it",
                )
                pos = end
                continue
            messages = []
            for record in records:
                if isinstance(record, Schema):
                    scan.schemas[record.id] = record
                elif isinstance(record, Channel):
                    scan.channels[record.id] = record
                elif isinstance(record, Message):
                    channel = scan.channels.get(record.channel_id)
                    if channel is None:
                        self._problem(scan, f"{scan.path}: message at byte {pos} names unknown channel "
                                            f"{record.channel_id}", "skipped it")
                        continue
                    messages.append((record, channel))
            count += len(messages)
            yield pos, times, messages
            pos = end
        scan.messages = count
        if scan.truncated or cut_at is not None:
            lost = "" if cut_at is None else f"; the last {size - cut_at} bytes (an incomplete record at byte {cut_at}) are lost"
            scan.recovered = f"{scan.path} {scan.truncated or 'is truncated or corrupt'}: recovered {count} messages{lost}"
            scan.damage = scan.damage or "is damaged before its first complete chunk"


@dataclass
class BagEpisode:
    """Messages of one episode: the /ad_sim/instance message and every other topic's messages."""

    instance: Any
    stamp_ns: int
    messages: dict[str, list[tuple[int, Any]]] = field(default_factory=dict)


def group_episodes(messages: Iterable[BagMessage], instance_topic: str = "/ad_sim/instance") -> Iterator[BagEpisode]:
    """Split a log-time-ordered message stream into episodes at each instance message.

    A message belongs to the latest instance stamped at or before it; messages before the
    first instance are dropped (a recording that started mid-episode), but for those stamped like it."""
    current: BagEpisode | None = None
    before_first: dict[str, list] = {}  # messages before any instance, of the latest stamp only
    for topic, stamp, message in messages:
        if topic == instance_topic:
            following = BagEpisode(message, stamp)
            # Frame-0 messages stamped like the instance may precede it in the file (a recorder writes in
            # the order messages arrive), the first episode's included.
            for name, items in (current.messages if current is not None else before_first).items():
                moved = []
                while items and items[-1][0] >= stamp:
                    moved.append(items.pop())
                if moved:
                    following.messages[name] = moved[::-1]
            if current is not None:
                yield current
            current = following
        elif current is not None:
            current.messages.setdefault(topic, []).append((stamp, message))
        else:
            if any(items[-1][0] < stamp for items in before_first.values()):
                before_first.clear()  # a later stamp: those before it cannot be the first instance's
            before_first.setdefault(topic, []).append((stamp, message))
    if current is not None:
        yield current


#: The ground truth's fields that name a simulation, for a ground truth without a generated message class.
SIMULATION_FIELDS = ("episode_id", "seed", "shape", "material", "parameter_names", "parameters")


def simulation_key(instance) -> tuple:
    """What makes two episodes the same simulation: their ground truth but for its stamp and episode index, which a
    copy of a recording or a looping simulator's replay changes, and its camera poses, whose number is the views
    recorded (the first views' are the same whatever that number). Episodes of one id and seed that differ
    otherwise (a parameter sweep of the node's single-instance mode, say) are distinct."""
    fields = getattr(type(instance), "__slots__", SIMULATION_FIELDS)
    return tuple((name, repr(getattr(instance, name, None))) for name in fields
                 if name not in ("header", "episode_index", "camera_poses"))


def distinct_episodes(episodes: Iterable[BagEpisode], collided) -> Iterator[BagEpisode]:
    """group_episodes' episodes but those that start at the stamp of another episode: the frames of all of
    them went to the last, mixed with its own, and which is whose cannot be told (a recording of several
    simulator runs, each stamping its episodes from 0 s). Each such group is passed to `collided(group,
    reason)` instead. Where a group is all one simulation (the same id, seed, shape, family and parameters: a run
    recorded twice, a ground truth received twice), the last, which holds its frames, is that episode; runs of one
    id and seed with other parameters (a sweep of the node's single-instance mode) are distinct."""
    for stamp, same in itertools.groupby(episodes, key=lambda ep: ep.stamp_ns):
        same = list(same)
        if len({simulation_key(ep.instance) for ep in same}) == 1:
            yield same[-1]
            continue
        collided(same, f"episodes {', '.join(ep.instance.episode_id for ep in same)} start at the same stamp "
                       f"({stamp / 1e9:.3f} s), so their frames cannot be told apart (several simulator runs "
                       "recorded into one bag? each run stamps its episodes from 0 s: record each run into its own "
                       "bag); skipped")


# --------------------------------------------------------------------------- CLI


def _info(path: Path) -> None:
    reader = BagReader(path, raw=True, recover=True)
    counts: dict[str, int] = {}
    first = last = None
    for topic, stamp, _ in reader:
        counts[topic] = counts.get(topic, 0) + 1
        first = stamp if first is None else first
        last = stamp
    types = reader.topics()
    print(f"bag: {path}\nfiles: {', '.join(str(p.name) for p in reader.files)}")
    print(f"messages: {sum(counts.values())}  start: {(first or 0) / 1e9:.3f} s  end: {(last or 0) / 1e9:.3f} s")
    for topic in sorted(types):
        print(f"  {topic:40s} {types[topic]:32s} {counts.get(topic, 0)}")


def repair(source: str | os.PathLike, out: str | os.PathLike, compression: str = "zstd") -> int:
    """Rewrites what is readable of a damaged bag (a killed recorder's, a corrupt copy) as a complete
    one at `out`: every file with its summary, metadata.yaml with the true counts, so that other
    readers (ros2 bag, rosbags, Foxglove) take it. Topics keep their type and the offered QoS that
    the source's metadata.yaml lists (the default profile, with a warning, where those are unusable);
    publish times become log times. What could not be read is
    warned about, as BagReader(recover=True) does (an unusable metadata.yaml included: the .mcap
    files beside it are read). Returns the number of messages written; BagUnreadable if nothing is
    readable. Whatever stops it (that, another BagError, an interrupt) leaves no bag at `out`."""
    reader = BagReader(source, raw=True, recover=True)
    listed = {entry["topic_metadata"]["name"]: entry["topic_metadata"]
              for entry in (reader.metadata or {}).get("topics_with_message_count", [])}
    out = Path(out)
    created = not out.exists()  # else an empty folder: BagWriter refuses anything else before writing

    def clean_up() -> None:  # what this call made: no empty or half-made bag in its place
        if created:
            shutil.rmtree(out, ignore_errors=True)
        elif out.is_dir():
            for path in out.iterdir():
                shutil.rmtree(path, ignore_errors=True) if path.is_dir() else path.unlink(missing_ok=True)

    count = 0
    try:  # before reading: a bad `out` fails at once
        writer = BagWriter(out, compression=compression, custom_data={"repaired_from": str(source)})
    except OSError as exc:  # a file on the way, a read-only or virtual file system, ...
        clean_up()
        raise BagError(f"cannot create bag output {out}: {exc.strerror or exc}") from None
    try:
        with writer:
            for topic, type_name in reader.topics().items():
                try:
                    qos = parse_offered_qos_profiles(listed.get(topic, {}).get("offered_qos_profiles"))
                except ValueError as exc:  # the messages matter more than how they were offered
                    warnings.warn(f"{reader.path / METADATA_FILE}: unusable offered_qos_profiles for {topic}: {exc}; "
                                  "the repaired bag lists the default profile for it")
                    qos = []
                writer.add_topic(topic, type_name, qos or None)
            for message in reader:
                writer.write(message.topic, message.log_time_ns, message.message)
                count += 1
    except BagWriteError as exc:  # a full disk: its advice on the files left does not apply, none are
        clean_up()
        cause = exc.__cause__
        raise BagError(f"cannot write the repaired bag {out}: {getattr(cause, 'strerror', None) or cause or exc}; "
                       "nothing is left there. Free space on that file system, or pass another --out") from None
    except BaseException:  # nothing readable, a file it cannot read, Ctrl-C, ...: no empty or partial bag in its place
        clean_up()
        raise
    return count


def one_line_warnings() -> None:
    """For command lines: print BagReader's warnings (recovered files, extra files) as
    `warning: <message>`, without Python's source-line decoration."""
    warnings.formatwarning = lambda message, *_args, **_kwargs: f"warning: {message}\n"


def main(argv: list[str] | None = None) -> int:
    one_line_warnings()
    parser = argparse.ArgumentParser(prog="python -m ad_sim.rosbag", description=__doc__.split("\n\n")[0])
    sub = parser.add_subparsers(dest="command", required=True)
    info = sub.add_parser("info", help="print the topics, types and message counts of a bag")
    info.add_argument("bag", type=Path, help="bag folder or .mcap file")
    fix = sub.add_parser("repair", help="rewrite what is readable of a damaged bag (a killed recorder's) as a "
                                        "complete bag that any reader takes")
    fix.add_argument("bag", type=Path, help="damaged bag folder or .mcap file")
    fix.add_argument("--out", type=Path, required=True, help="new bag folder (must not exist)")
    vendor = sub.add_parser("vendor-schemas", help="regenerate ad_sim/data/schemas from the installed ROS interfaces")
    vendor.add_argument("--out", type=Path, default=SCHEMA_DIR, help="output folder (default: %(default)s)")
    args = parser.parse_args(argv)
    try:
        if args.command == "info":
            _info(args.bag)
        elif args.command == "repair":
            print(f"{args.out}: {repair(args.bag, args.out)} messages written")
        else:
            for path in vendor_schemas(args.out):
                print(path)
    except BagError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())

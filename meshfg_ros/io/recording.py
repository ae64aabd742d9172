"""rosbag2 recordings (MCAP by default, as Jazzy's `ros2 bag`) with the pure-Python rosbags.

RecordingWriter embeds each message definition (meshfg_msgs included) in the file, so any
rosbag2/MCAP reader decodes it without meshfg_msgs installed. RecordingReader decodes with
the definitions embedded in the recording (falling back to the Jazzy + meshfg_msgs typestore
for recordings without any) and turns known messages into the plain records of
`meshfg_ros.io.messages`. Every failure is a RecordingError subclass with a one-line message.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypeVar

from rosbags.highlevel import AnyReader
from rosbags.interfaces import Connection
from rosbags.rosbag2 import CompressionFormat, CompressionMode, StoragePlugin, Writer, WriterError

from meshfg_ros.io.messages import (
    ESTIMATOR_STATUS,
    POINT_CLOUD2,
    POSE_STAMPED,
    TETRA_MESH,
    MeshState,
    MessageValidationError,
    PointCloudRecord,
    PoseRecord,
    RosbagsMessageFactory,
    StatusRecord,
    mesh_state_from_msg,
    mesh_state_to_msg,
    readable_definition_hashes,
    meshfg_typestore,
    pose_from_msg,
    pose_to_msg,
    stamp_ns_from_msg,
    status_from_msg,
    status_to_msg,
)
from meshfg_ros.io.pointcloud import PointCloudError, cloud_record_from_msg, cloud_record_to_msg

RecordT = TypeVar("RecordT", MeshState, StatusRecord, PoseRecord, PointCloudRecord)

# Record class -> (ROS message type, record -> rosbags message, message -> record).
RECORD_TYPES: dict[type, tuple[str, Callable[..., Any], Callable[[Any], Any]]] = {
    MeshState: (TETRA_MESH, mesh_state_to_msg, mesh_state_from_msg),
    StatusRecord: (ESTIMATOR_STATUS, status_to_msg, status_from_msg),
    PoseRecord: (POSE_STAMPED, pose_to_msg, pose_from_msg),
    PointCloudRecord: (POINT_CLOUD2, cloud_record_to_msg, cloud_record_from_msg),
}
_FROM_MSG = {msgtype: from_msg for msgtype, _, from_msg in RECORD_TYPES.values()}
_STORAGES = {"mcap": StoragePlugin.MCAP, "sqlite3": StoragePlugin.SQLITE3}


class RecordingError(Exception):
    """Base of every recording failure; the message is one line, fit for a CLI."""


class RecordingNotFoundError(RecordingError):
    """The recording path does not exist."""


class NotARecordingError(RecordingError):
    """The path exists but is not a rosbag2 directory (no metadata.yaml)."""


class CorruptRecordingError(RecordingError):
    """The recording's metadata or storage cannot be read or decoded."""


class EmptyRecordingError(RecordingError):
    """The recording is readable but holds no messages."""


class TopicNotFoundError(RecordingError):
    """A requested topic is not in the recording."""


class TopicTypeError(RecordingError):
    """A topic holds (or would get) another message type, or an incompatible definition of it."""


class InvalidRecordedMessageError(RecordingError):
    """A recorded message decodes but its content is invalid (e.g. a mesh index out of range)."""


class RecordingExistsError(RecordingError):
    """The output path exists already; recordings are never overwritten."""


class UnsupportedMessageError(RecordingError):
    """The object to write is neither a record nor a message of the typestore."""


@dataclass(frozen=True)
class TopicInfo:
    """One topic of a recording: its message type and how many messages it holds."""

    name: str
    msgtype: str
    count: int


@dataclass(frozen=True)
class RecordedMessage:
    """One message in log-time order: a record for known types, else the decoded message."""

    topic: str
    msgtype: str
    log_time_ns: int
    data: Any


class RecordingWriter:
    """Writes a new rosbag2 recording (context manager); never overwrites an existing path.

    write(topic, record_or_message, stamp_ns) takes the plain records of
    `meshfg_ros.io.messages` or any rosbags message of the Jazzy + meshfg_msgs typestore.
    compress=True zstd-compresses MCAP chunks (as `ros2 bag record --storage-preset-profile
    zstd_fast`); every MCAP reader decodes them.
    Leaving the `with` block finalises the recording, also after an exception, so what was
    written before a failure stays readable.
    """

    def __init__(self, path: str | Path, storage: str = "mcap", compress: bool = False) -> None:
        self.path = Path(path)
        if storage not in _STORAGES:
            raise ValueError(f"unknown storage {storage!r}; expected one of {sorted(_STORAGES)}")
        if compress and storage != "mcap":
            raise ValueError("compress=True needs MCAP storage (zstd-compressed chunks)")
        if self.path.exists() or self.path.is_symlink():
            raise RecordingExistsError(f"{self.path} exists already; recordings are never overwritten")
        self._typestore = meshfg_typestore()
        self._factory = RosbagsMessageFactory(self._typestore)
        self._writer = Writer(self.path, version=9, storage_plugin=_STORAGES[storage])
        if compress:
            self._writer.set_compression(CompressionMode.STORAGE, CompressionFormat.ZSTD)
        self._connections: dict[str, Connection] = {}
        self.counts: dict[str, int] = {}

    def __enter__(self) -> RecordingWriter:
        try:
            self._writer.open()
        except WriterError as error:
            raise RecordingExistsError(str(error)) from None
        return self

    def __exit__(self, exc_type: Any, exc_value: Any, traceback: Any) -> None:
        self.close()

    def close(self) -> None:
        """Finalise the recording (index, metadata.yaml); aborts it if that fails."""
        if self._writer.storage is None:
            return
        try:
            self._writer.close()
        except BaseException:
            self._writer.abort()
            raise

    def write(self, topic: str, data: Any, stamp_ns: int | None = None) -> None:
        """Append `data` (record or rosbags message) on `topic` at log time `stamp_ns`.

        stamp_ns defaults to the record's stamp, or to the message's header stamp.
        """
        if self._writer.storage is None:
            raise RecordingError(f"{self.path} is not open for writing (use RecordingWriter in a with block)")
        if type(data) in RECORD_TYPES:
            msgtype, to_msg, _ = RECORD_TYPES[type(data)]
            message = to_msg(data, self._factory)
            default_stamp = data.stamp_ns
        elif getattr(type(data), "__msgtype__", None) in self._typestore.types:
            msgtype, message = type(data).__msgtype__, data
            header = getattr(data, "header", None)
            default_stamp = None if header is None else stamp_ns_from_msg(header.stamp)
        else:
            raise UnsupportedMessageError(
                f"cannot record a {type(data).__name__} on {topic}: expected a meshfg record or a rosbags message"
            )
        stamp_ns = default_stamp if stamp_ns is None else int(stamp_ns)
        if stamp_ns is None:
            raise ValueError(f"{topic}: pass stamp_ns, a {msgtype} has no header stamp")
        if stamp_ns < 0:
            raise ValueError(f"{topic}: log time {stamp_ns} ns is negative")
        connection = self._connections.get(topic)
        if connection is None:
            connection = self._writer.add_connection(topic, msgtype, typestore=self._typestore)
            self._connections[topic] = connection
            self.counts[topic] = 0
        elif connection.msgtype != msgtype:
            raise TopicTypeError(f"topic {topic} holds {connection.msgtype}, cannot write a {msgtype} to it")
        self._writer.write(connection, stamp_ns, self._typestore.serialize_cdr(message, msgtype))
        self.counts[topic] += 1


class RecordingReader:
    """Reads a rosbag2 recording (directory with metadata.yaml; MCAP or sqlite3 storage).

    Opened on construction; use as a context manager or call close().
    """

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        if not self.path.exists():
            raise RecordingNotFoundError(f"recording {self.path} does not exist")
        if not (self.path / "metadata.yaml").is_file():
            raise NotARecordingError(f"{self.path} is not a rosbag2 recording (no metadata.yaml)")
        self._reader = AnyReader([self.path], default_typestore=meshfg_typestore())
        try:
            self._reader.open()
        except Exception as error:  # anything a parser raises on these bytes means a bad file
            raise CorruptRecordingError(f"cannot open recording {self.path}: {_one_line(error)}") from None
        try:
            self._index_topics()
        except BaseException:
            self.close()
            raise

    def _index_topics(self) -> None:
        """Fill topics, counts and times; check definitions of the types converted to records."""
        self.topics: dict[str, TopicInfo] = {}
        for connection in self._reader.connections:
            info = self.topics.get(connection.topic, TopicInfo(connection.topic, connection.msgtype, 0))
            if info.msgtype != connection.msgtype:
                raise CorruptRecordingError(
                    f"{self.path}: topic {info.name} has two types, {info.msgtype} and {connection.msgtype}"
                )
            self.topics[info.name] = TopicInfo(info.name, info.msgtype, info.count + connection.msgcount)
        try:
            self._compatible_types = {
                msgtype
                for msgtype in {info.msgtype for info in self.topics.values()} & set(_FROM_MSG)
                if self._reader.typestore.hash_rihs01(msgtype) in readable_definition_hashes().get(
                    msgtype, {meshfg_typestore().hash_rihs01(msgtype)})
            }
        except Exception as error:  # a definition the recording lacks or that does not parse
            raise CorruptRecordingError(
                f"{self.path} has unusable message definitions: {_one_line(error)}"
            ) from None
        self.message_count = sum(info.count for info in self.topics.values())
        if self.message_count == 0:
            raise EmptyRecordingError(f"recording {self.path} holds no messages")
        self.start_ns = self._reader.start_time
        self.end_ns = self._reader.end_time - 1

    def __enter__(self) -> RecordingReader:
        return self

    def __exit__(self, exc_type: Any, exc_value: Any, traceback: Any) -> None:
        self.close()

    def close(self) -> None:
        """Release the storage files."""
        if self._reader.stack is not None:
            self._reader.close()

    def require(self, topic: str, record_type: type | None = None) -> TopicInfo:
        """Check that `topic` exists (and holds `record_type`'s message type, compatibly)."""
        if topic not in self.topics:
            raise TopicNotFoundError(
                f"topic {topic} is not in {self.path} (topics: {', '.join(sorted(self.topics))})"
            )
        info = self.topics[topic]
        if record_type is not None:
            expected = RECORD_TYPES[record_type][0]
            if info.msgtype != expected:
                raise TopicTypeError(f"topic {topic} holds {info.msgtype}, expected {expected}")
        if info.msgtype in _FROM_MSG and info.msgtype not in self._compatible_types:
            raise TopicTypeError(
                f"topic {topic}: the recorded {info.msgtype} definition differs from this version's"
            )
        return info

    def messages(
        self,
        topics: Iterable[str] | None = None,
        start_ns: int | None = None,
        stop_ns: int | None = None,
    ) -> Iterator[RecordedMessage]:
        """Messages of `topics` (all by default) with start_ns <= log time < stop_ns, in time order.

        Messages of TetraMesh, EstimatorStatus, PoseStamped and PointCloud2 come as records.
        """
        names = sorted(self.topics) if topics is None else list(dict.fromkeys(topics))
        for name in names:
            self.require(name)
        connections = [c for c in self._reader.connections if c.topic in names]
        return self._decoded(self._reader.messages(connections, start=start_ns, stop=stop_ns))

    def records(self, topic: str, record_type: type[RecordT]) -> Iterator[RecordT]:
        """The records of one topic in time order (checks first that it holds `record_type`)."""
        self.require(topic, record_type)
        return (recorded.data for recorded in self.messages([topic]))

    def _decoded(self, stream: Iterator[tuple[Connection, int, bytes]]) -> Iterator[RecordedMessage]:
        """Deserialise raw messages and convert known types to records."""
        while True:
            try:
                connection, log_time, raw = next(stream)
                message = self._reader.deserialize(raw, connection.msgtype)
            except StopIteration:
                return
            except Exception as error:  # anything a parser raises on these bytes means a bad file
                raise CorruptRecordingError(f"{self.path} is corrupt: {_one_line(error)}") from None
            from_msg = _FROM_MSG.get(connection.msgtype)
            if from_msg is not None:
                try:
                    message = from_msg(message)
                except (MessageValidationError, PointCloudError) as error:
                    raise InvalidRecordedMessageError(
                        f"{connection.topic} at {log_time} ns: {_one_line(error)}"
                    ) from None
            yield RecordedMessage(connection.topic, connection.msgtype, log_time, message)


def _one_line(error: BaseException) -> str:
    return " ".join(str(error).split()) or type(error).__name__

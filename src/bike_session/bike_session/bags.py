"""Reading recorded bike sessions (rosbag2 directories, MCAP or sqlite3, or a bare .mcap file).

The typestore is built from the message definitions EMBEDDED in the bag, so reading needs
neither ROS nor this workspace (only rosbags, and mcap for a bare .mcap file).

    with open_bag("runs/session_x") as bag:
        print(bag.topics)                     # {'/bike/command': ('bike_msgs/msg/Command', 601), ...}
        for topic, t_ns, msg in bag.messages(["command"]):
            ...
    msgs = read_topic("runs/session_x", "plant_state")      # relative names match /<ns>/<name>
    ps = plant_state_array("runs/session_x")                  # numpy structured array

Every problem (missing path, not a bag, unclosed or truncated recording, undecodable
data) raises :class:`BagError` with the path and a clear reason.
"""
from __future__ import annotations

import os
import pathlib
import struct
from typing import Iterable, Iterator

import numpy as np


# An MCAP chunk's records, decompressed. rosbags' zstd / lz4 decompression has no bound (a
# 35 kB chunk of RLE blocks inflated to 1 GB, 2.1 GB of memory, before its size was checked) and
# mcap's takes the chunk's own declared size: both are checked here first, streamed.
MAX_CHUNK_BYTES = 256 * 2**20
_INFLATE_STEP_BYTES = 2**20


class BagError(Exception):
    """A bag that cannot be read, with the path and the reason."""

    def __init__(self, message: str, path: str | os.PathLike | None = None):
        super().__init__(f"{path}: {message}" if path is not None else message)
        self.path = path


def _bags_in(folder: pathlib.Path) -> list[str]:
    """Names of the closed rosbag2 bags directly in ``folder``, sorted (session_<UTC time> sorts
    by time); [] when it cannot be listed."""
    try:
        return sorted(p.name for p in folder.iterdir() if (p / "metadata.yaml").is_file())
    except OSError:
        return []


class Bag:
    """An open bag: topics, time range, decoded messages in log-time order."""

    def __init__(self, path: str | os.PathLike):
        self.path = pathlib.Path(path)
        self._reader = None
        self._mcap_file = None
        if not self.path.exists():
            raise BagError("no such bag (path does not exist)", self.path)
        if self.path.is_file():
            if self.path.suffix == ".mcap":
                self._open_mcap_file()
                return
            if self.path.name == "metadata.yaml":
                self.path = self.path.parent
            else:
                raise BagError("not a bag: expected a rosbag2 directory (with metadata.yaml) or a .mcap file",
                               self.path)
        if not (self.path / "metadata.yaml").is_file():
            hint = ""
            if any(self.path.glob("*.mcap")) or any(self.path.glob("*.db3")):
                hint = (" (data files are present: the recording was not closed properly; "
                        f"./bike bag recover {self.path} rescues what it flushed)")
            else:
                # `./bike report runs` (the folder make demo records into): name the bags in it
                bags = _bags_in(self.path)
                if len(bags) == 1:
                    hint = f" (a folder holding the bag {self.path / bags[0]}: give that)"
                elif bags:
                    hint = f" (a folder holding {len(bags)} bags: give one, e.g. {self.path / bags[-1]})"
            raise BagError(f"not a rosbag2 bag: metadata.yaml missing{hint}", self.path)
        self._open_rosbag2()

    # ------------------------------------------------------------------ opening
    def _open_rosbag2(self) -> None:
        from rosbags.highlevel import AnyReader

        _check_mcap_chunks(sorted(self.path.glob("*.mcap")))
        try:
            reader = AnyReader([self.path])
            reader.open()
        except Exception as exc:  # noqa: BLE001 - rosbags raises many error classes
            # a data file cut short (a copy or disk that ran out, a crash after the metadata)
            # reads as "File end magic is invalid": say where the rescue is
            reason = _reason(exc).rstrip(".")
            hint = ""
            if any(self.path.glob("*.mcap")) or any(self.path.glob("*.db3")):
                # rosbags' "Invalid bag metadata: 'NoneType' object is not subscriptable" or "A metadata
                # key is missing" is metadata.yaml's damage, not a data file's: recover rebuilds it too
                hint = ("; its metadata.yaml is damaged: ./bike bag recover rebuilds the bag from the data files"
                        if "metadata" in reason.lower() else
                        "; if its data file was cut short, ./bike bag recover rescues what survived")
            raise BagError(f"cannot open bag: {reason}{hint}", self.path) from None
        self._reader = reader
        self.typestore = reader.typestore
        self._connections = reader.connections
        self.topics = {}
        for c in reader.connections:
            msgtype, count = self.topics.get(c.topic, (c.msgtype, 0))
            self.topics[c.topic] = (msgtype, count + c.msgcount)
        self.start_ns = reader.start_time if reader.message_count else 0
        self.end_ns = reader.end_time if reader.message_count else 0

    def _open_mcap_file(self) -> None:
        from rosbags.typesys import Stores, get_types_from_msg, get_typestore

        try:
            from mcap.reader import make_reader
        except ImportError:
            raise BagError("reading a bare .mcap file needs the 'mcap' package", self.path) from None
        _check_mcap_chunks([self.path])
        try:
            fh = open(self.path, "rb")
            reader = make_reader(fh)
            summary = reader.get_summary()
        except Exception as exc:  # noqa: BLE001
            raise BagError(f"cannot read MCAP file: {_reason(exc)}", self.path) from None
        if summary is None:
            fh.close()
            raise BagError("MCAP file has no summary (truncated or unclosed recording)", self.path)
        types = {}
        self.topics = {}
        self._channel_type = {}
        try:
            for ch in summary.channels.values():
                schema = summary.schemas.get(ch.schema_id)
                if schema is None or schema.encoding not in ("ros2msg",):
                    raise BagError(f"channel {ch.topic} has no ros2msg schema", self.path)
                types.update(get_types_from_msg(schema.data.decode(), schema.name))
                count = (summary.statistics.channel_message_counts.get(ch.id, 0)
                         if summary.statistics else 0)
                msgtype, prev = self.topics.get(ch.topic, (schema.name, 0))
                self.topics[ch.topic] = (msgtype, prev + count)
                self._channel_type[ch.id] = schema.name
        except BagError:
            fh.close()
            raise
        except Exception as exc:  # noqa: BLE001
            fh.close()
            raise BagError(f"bad embedded message definition: {_reason(exc)}", self.path) from None
        ts = get_typestore(Stores.EMPTY)
        ts.register(types)
        self.typestore = ts
        self._mcap_file = fh
        self._mcap_reader = reader
        st = summary.statistics
        self.start_ns = st.message_start_time if st else 0
        self.end_ns = st.message_end_time if st else 0

    # ------------------------------------------------------------------ API
    def __enter__(self) -> "Bag":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        if self._reader is not None:
            try:
                self._reader.close()
            except Exception:  # noqa: BLE001
                pass
            self._reader = None
        if self._mcap_file is not None:
            self._mcap_file.close()
            self._mcap_file = None

    @property
    def duration_s(self) -> float:
        return max(self.end_ns - self.start_ns, 0) * 1e-9

    def message_counts(self) -> dict[str, int]:
        return {topic: count for topic, (_, count) in self.topics.items()}

    def resolve(self, topic: str) -> str:
        """Full topic name; a relative name matches exactly one ``/<ns>/<name>`` in the bag."""
        if topic in self.topics:
            return topic
        if not topic.startswith("/"):
            matches = [t for t in self.topics if t.rsplit("/", 1)[-1] == topic or t.endswith("/" + topic)]
            if len(matches) == 1:
                return matches[0]
            if len(matches) > 1:
                raise BagError(f"topic {topic!r} is ambiguous: {', '.join(sorted(matches))}", self.path)
        raise BagError(f"no topic {topic!r} in the bag; topics: {', '.join(sorted(self.topics)) or 'none'}",
                       self.path)

    def messages(self, topics: Iterable[str] | None = None, raw: bool = False) -> Iterator[tuple[str, int, object]]:
        """Yield (topic, log_time_ns, message) in log-time order (raw=True: CDR bytes)."""
        wanted = None if topics is None else {self.resolve(t) for t in topics}
        try:
            if self._reader is not None:
                conns = [c for c in self._connections if wanted is None or c.topic in wanted]
                for conn, t_ns, data in self._reader.messages(connections=conns):
                    yield conn.topic, t_ns, (data if raw else self._reader.deserialize(data, conn.msgtype))
            elif self._mcap_file is not None:
                for _schema, ch, m in self._mcap_reader.iter_messages(topics=list(wanted) if wanted else None):
                    data = m.data
                    yield ch.topic, m.log_time, (data if raw else
                                                 self.typestore.deserialize_cdr(data, self._channel_type[ch.id]))
            else:
                raise BagError("bag is closed", self.path)
        except BagError:
            raise
        except Exception as exc:  # noqa: BLE001 - truncated chunks, bad CDR, sqlite errors
            raise BagError(f"cannot read messages: {_reason(exc)}", self.path) from None


def _inflated_bytes(fh, compression: str, size: int, cap: int) -> int:
    """Bytes the ``size`` compressed bytes at ``fh`` inflate to (frame after frame, as the readers
    take them), counted in steps and stopped once past ``cap`` (nothing kept); -1 for a
    compression this check does not know (the readers refuse it)."""
    if compression == "zstd":
        try:
            from compression import zstd
        except ImportError:
            from backports import zstd
        new = zstd.ZstdDecompressor
    elif compression == "lz4":
        import lz4.frame
        new = lz4.frame.LZ4FrameDecompressor
    else:
        return -1
    dec, out, pending = new(), 0, b""
    try:
        while out <= cap:
            if not pending:
                pending = fh.read(min(size, _INFLATE_STEP_BYTES)) if size > 0 else b""
                if not pending:
                    break
                size -= len(pending)
            step = len(dec.decompress(pending, _INFLATE_STEP_BYTES))
            out, pending = out + step, b""
            while out <= cap and step and not dec.eof and not dec.needs_input:
                step = len(dec.decompress(b"", _INFLATE_STEP_BYTES))
                out += step
            if dec.eof:                               # the next frame, if any
                pending, dec = dec.unused_data, new()
    except Exception:  # noqa: BLE001 - corrupt data: the readers' own error says so
        pass
    return out


def mcap_chunk_problem(path: str | os.PathLike) -> tuple[int, str] | None:
    """(byte offset, reason) of the first Chunk record of the MCAP file ``path`` that declares or
    inflates to more than MAX_CHUNK_BYTES or to more than it declares, or of a ChunkIndex that
    does not describe a chunk checked so; None if there is none. Reads the records' headers
    and streams compressed chunks in 1 MB steps: memory stays bounded whatever the file claims.
    A torn record ends the walk (the readers report it, ``bag recover`` keeps what precedes it)."""
    try:
        return _walk_mcap_chunks(path)
    except struct.error:                                # a field past the file's end: the readers say so
        return None


def _walk_mcap_chunks(path) -> tuple[int, str] | None:
    chunks = {}
    with open(path, "rb") as fh:
        end = os.fstat(fh.fileno()).st_size
        pos = 8                                         # after the magic
        while pos + 9 <= end:
            fh.seek(pos)
            opcode, length = struct.unpack("<BQ", fh.read(9))
            body = pos + 9
            if body + length > end:
                break
            if opcode == 0x06 and length >= 40:         # Chunk
                _start, _stop, declared, _crc, name_len = struct.unpack("<QQQII", fh.read(32))
                if name_len > 64:
                    return pos, f"chunk at byte {pos}: compression name of {name_len} bytes"
                compression = fh.read(name_len).decode("utf-8", "replace")
                (size,) = struct.unpack("<Q", fh.read(8))
                if declared > MAX_CHUNK_BYTES:
                    return pos, (f"chunk at byte {pos} declares {declared} bytes of records: past the "
                                 f"{MAX_CHUNK_BYTES} this reader inflates")
                if compression and size <= length:
                    cap = min(declared, MAX_CHUNK_BYTES)
                    out = _inflated_bytes(fh, compression, size, cap)
                    if out > cap:
                        return pos, (f"chunk at byte {pos} inflates past the {declared} bytes it declares "
                                     f"(bound {MAX_CHUNK_BYTES}): a decompression bomb or a corrupt chunk")
                chunks[pos] = (compression, size, declared)
            elif opcode == 0x08 and length >= 48:       # ChunkIndex (summary): what the readers seek by
                _start, _stop, offset, _length, map_len = struct.unpack("<QQQQI", fh.read(36))
                if 36 + map_len + 8 + 4 > length:
                    return pos, f"chunk index at byte {pos}: its offsets map overruns the record"
                fh.seek(map_len + 8, 1)
                (name_len,) = struct.unpack("<I", fh.read(4))
                compression = fh.read(min(name_len, 64)).decode("utf-8", "replace")
                size, declared = struct.unpack("<QQ", fh.read(16)) if name_len <= 64 else (-1, -1)
                if chunks.get(offset) != (compression, size, declared):
                    return pos, (f"chunk index at byte {pos} does not describe the chunk at byte {offset} "
                                 f"(its sizes or compression differ, or no chunk starts there): not inflated")
            elif opcode == 0x02:                        # Footer
                break
            pos = body + length
    return None


def _check_mcap_chunks(files) -> None:
    for path in files:
        try:
            problem = mcap_chunk_problem(path)
        except OSError as exc:
            raise BagError(f"cannot read: {exc.strerror or exc}", path) from None
        if problem is not None:
            raise BagError(problem[1], path)


def _reason(exc: BaseException) -> str:
    if isinstance(exc, MemoryError):
        # a flipped length field asks for more than memory holds (the allocation fails at once)
        return "a record claims more bytes than memory holds: a corrupt or hostile file"
    text = str(exc).strip() or type(exc).__name__
    return text.splitlines()[0][:300]


def open_bag(path: str | os.PathLike) -> Bag:
    """Open a bag directory (rosbag2, MCAP or sqlite3) or a bare .mcap file; BagError on failure."""
    return Bag(path)


def read_topic_stamped(path: str | os.PathLike, topic: str) -> list[tuple[int, object]]:
    """[(log_time_ns, message)] of one topic (relative names allowed)."""
    with open_bag(path) as bag:
        return [(t, msg) for _, t, msg in bag.messages([topic])]


def read_topic(path: str | os.PathLike, topic: str) -> list:
    """Decoded messages of one topic, in log-time order (relative names allowed)."""
    return [msg for _, msg in read_topic_stamped(path, topic)]


def stamp_s(msg) -> float:
    """header.stamp of a decoded message in seconds."""
    st = msg.header.stamp
    return st.sec + st.nanosec * 1e-9


PLANT_STATE_DTYPE = np.dtype([
    ("time_s", "f8"), ("seq", "u8"), ("end_of_run", "?"),
    ("speed_rpm", "f8"), ("speed_rad_s", "f8"),
    ("torque_em_nm", "f8"), ("load_torque_nm", "f8"),
    ("dc_bus_v", "f8"), ("brake_resistor_on", "?"),
    ("battery_ocv_v", "f8"), ("battery_soc", "f8"), ("battery_current_a", "f8"),
    ("energy_mech_in_j", "f8"), ("energy_battery_j", "f8"), ("energy_resistor_j", "f8"),
    ("energy_loss_j", "f8"), ("energy_stored_j", "f8"),
    ("faults", "u4"), ("interlock_blanked_count", "u8"),
    ("phase_current_peak_a", "f8"),   # max |i| over phase_current_a and current_samples_a
])


def plant_state_rows(messages: Iterable) -> np.ndarray:
    """Structured array (PLANT_STATE_DTYPE) from decoded PlantState messages."""
    rows = []
    for m in messages:
        peak = float(np.max(np.abs(np.asarray(m.phase_current_a, dtype=float)))) if len(m.phase_current_a) else 0.0
        samples = np.asarray(m.current_samples_a, dtype=float)
        if samples.size:
            peak = max(peak, float(np.max(np.abs(samples))))
        rows.append((stamp_s(m), m.seq, m.end_of_run, m.speed_rpm, m.speed_rad_s, m.torque_em_nm,
                     m.load_torque_nm, m.dc_bus_v, m.brake_resistor_on, m.battery_ocv_v, m.battery_soc,
                     m.battery_current_a, m.energy_mech_in_j, m.energy_battery_j, m.energy_resistor_j,
                     m.energy_loss_j, m.energy_stored_j, m.faults, m.interlock_blanked_count, peak))
    arr = np.array(rows, dtype=PLANT_STATE_DTYPE)
    return arr[np.argsort(arr["time_s"], kind="stable")] if arr.size else arr


def plant_state_array(path: str | os.PathLike, topic: str = "plant_state") -> np.ndarray:
    """PlantState fields of a bag as a numpy structured array, sorted by header time."""
    return plant_state_rows(read_topic(path, topic))

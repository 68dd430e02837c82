"""Recorder node: writes every topic of one bike to a rosbag2 bag (MCAP or sqlite3).

Node name ``recorder`` (namespace ``/bike`` by default). Parameters:

- ``record_dir`` (string, "."): folder of the bag; created if missing.
- ``bag_name`` (string, "" -> ``session_<UTC timestamp>``): the bag directory inside record_dir.
- ``storage`` (string, "mcap" | "sqlite3").
- ``stop_on_end_of_run`` (bool, false): exit by itself once PlantState.end_of_run is recorded.
- ``flush_period_s`` (float, 0.5): crash safety. At least this often, in sim time and in wall
  time, the open MCAP chunk is closed and written out (sqlite3: the transaction is
  committed) and the file is fsync'ed. A recorder killed with kill -9 therefore loses at
  most this much data; ``./bike bag recover BAG`` turns what survived into a normal bag.
- ``writers_wait_s`` (float, 5): how long seq 0 waits to be confirmed on ``recorder_progress``
  until the session's Command and session_info writers have matched this recorder and sent it
  their first message (and every writer the graph lists on a recorded topic has matched it;
  see Flow control).

Flow control: after every ``PROGRESS_EVERY`` PlantStates written (and at end of run) the node
publishes the last written ``seq`` on ``recorder_progress`` (std_msgs/UInt64). A lockstep plant
with ``recorder_window_batches`` > 0 never runs more than that many batches ahead of it, so a
recorder that is slower than the loop (a loaded machine, a slow disk) slows the run down
instead of losing messages from a DDS history. Seq 0 is confirmed (the plant holds seq 1
until then) only once the session's writers have matched and delivered their first message
(and the graph's others have matched), at most ``writers_wait_s``: nothing else orders the
session-recorder match before the run, and a short run could end before it, leaving a bag
without Commands.

Subscriptions take the serialized CDR bytes (``raw=True``): nothing is deserialized. The
bag is written with rosbags (format version 9, rosbag2 Jazzy) and embeds the message
definitions (bike_msgs from the installed .msg files), so ROS 2 tools, MCAP viewers and
:mod:`bike_session.bags` read it without the workspace. Log time = sim time: the header
stamp of messages that have one, the clock value for /clock, the latest clock otherwise.
A PlantState or /clock byte-identical to the one before it on its topic is the lockstep
plant re-publishing an unanswered batch (and a DriveCommand or ControllerStatus likewise the
controller's answer to it, sent again; a BatteryState likewise the plant's seq 0 sent again
for a reader that matched late), and a Command byte-identical to one of the last
``RESENT_COMMAND_WINDOW`` is the session sending the Commands in force again for a reader
that matched late; both are counted, not written (two runs' bags stay identical).

A plant restarted mid-run starts a new run at seq 0 (its machine state died with it): at a
PlantState seq 0 after a later seq of the same run, the bag is closed and the new run goes
to a new one beside it, ``<bag_name>_run2`` (then ``_run3``, ...), which gets the latched
session_info again. Each bag then holds one run from t = 0; the first ends without an
end_of_run state (the plant died). A ``bag: PATH`` line on stdout names each new bag.

On SIGINT / SIGTERM the node keeps spinning until the PlantState with ``end_of_run``
has been recorded or 3 s pass without any message, then closes the bag and exits 0.
The first line on stdout is ``bag: PATH``.
"""
from __future__ import annotations

import collections
import datetime as _dt
import glob
import importlib
import os
import pathlib
import signal
import struct
import sys
import time
from typing import Iterable

# (topic relative to the bike namespace unless absolute, ROS type, has std_msgs/Header first)
TOPICS: tuple[tuple[str, str, bool], ...] = (
    ("command", "bike_msgs/msg/Command", True),
    ("plant_state", "bike_msgs/msg/PlantState", True),
    ("drive_command", "bike_msgs/msg/DriveCommand", True),
    ("controller_status", "bike_msgs/msg/ControllerStatus", True),
    ("session_status", "bike_msgs/msg/SessionStatus", True),
    ("session_info", "std_msgs/msg/String", False),
    ("battery", "sensor_msgs/msg/BatteryState", True),
    ("/clock", "rosgraph_msgs/msg/Clock", True),         # Clock's first field is a Time, like a header
    ("/diagnostics", "diagnostic_msgs/msg/DiagnosticArray", True),
    # an emulated drive's physics (bike-drive-emulator --truth-topic): the report's true rider power
    ("drive_truth", "bike_msgs/msg/DriveTruth", True),
)
LATCHED_TOPICS = {"session_info"}
# The session publishes these transient_local (keep_last 100), and the drive emulator its truth
# (keep_last 1000): a recorder whose reader matches late still receives the first ones. If a
# volatile publisher appears on one of them (a replayer), the incompatible-QoS event switches
# that subscription to volatile. The bag records them as offered transient_local (BagSink).
PREFER_LATCHED = {"command", "session_status", "drive_truth"}
QOS_DEPTH = 1000
PROGRESS_EVERY = 10
RESENT_COMMAND_WINDOW = 16          # the session re-sends at most the 2 Commands in force
SILENCE_S = 3.0
# Lockstep: seq 0 is confirmed (the plant holds seq 1 until then) only once the session's
# Command and session_info writers, and every writer the graph lists, have matched this
# recorder, at most this long (below the plant's recorder_timeout_s, 10 s by default). The
# plant waits for the recorder's reader of its states, and the controller for the session's
# Commands, but nothing waited for the session-recorder match: a 1.2 s run on a busy host
# ended before it, and the bag had no Commands (CI, 2026-12-07).
WRITERS_WAIT_S = 5.0
# after a burst, let the next samples gather this long before taking them: waking for every
# message (3 per lockstep batch) cost the 2 cores the loop needs. 3 ms is a few batches,
# far inside the plant's recorder window (50 batches) and the readers' depth (QOS_DEPTH).
# Measured, recorded 20 s demo: 0.97-0.98x real time waking per message, 1.09-1.21x gathering.
GATHER_S = 0.003
# a running recorder that starts over on fresh ports (_hand_over) records on with the old
# participant until the new one's readers have matched as many writers (at most
# bike_plant.loop.HANDOVER_WAIT_S), and then drops what the new one takes that the old one
# wrote (its readers' queue, and the transient_local history it gets at its match) for this long
HANDOVER_DEDUP_S = 5.0
# what a recorder's new node takes over from the old one at the hand-over (_hand_over)
RECORDING_STATE = ("sink", "bag_paths", "run_seq_max", "_latched_raw", "_dropped_since_state", "latest_clock_ns",
                   "last_msg_wall", "heard_any", "end_of_run_seen", "bad_stamps", "republished_dropped", "_last_raw",
                   "resent_commands_dropped", "plant_states_written", "_pending_progress", "_writers_matched",
                   "_hold_since", "handover")
STORAGES = ("mcap", "sqlite3")


class SetupError(Exception):
    """A start-up problem reported as one line on stderr (exit code 2)."""


class HandOverLog:
    """What a recorder wrote, per topic, so that a new participant on fresh ports (_hand_over)
    writes nothing twice: the durable topics' last QOS_DEPTH messages always (their history
    comes again at the new reader's match), every topic's while both participants listen
    (:meth:`start`), and the copies the new one takes for HANDOVER_DEDUP_S after it takes over
    (:meth:`open_window`) are dropped. Then only the durable topics are kept again."""

    def __init__(self, durable_topics):
        self.durable = set(durable_topics)
        self.seen: dict[str, dict] = {t: {} for t in self.durable}     # insertion-ordered sets of raw messages
        self.capped = True
        self.dedup_until = 0.0
        self.dropped = 0

    def start(self, topics) -> None:
        for topic in topics:
            self.seen.setdefault(topic, {})
        self.capped = False

    def open_window(self, now: float) -> None:
        self.dedup_until = now + HANDOVER_DEDUP_S

    def again(self, topic: str, raw: bytes, now: float) -> bool:
        """True when ``raw`` is a copy to drop (written before the hand-over); else remembers it."""
        seen = self.seen[topic]
        if raw in seen:
            if now < self.dedup_until:
                self.dropped += 1
                return True
            return False
        seen[raw] = None
        if not self.capped and self.dedup_until and now >= self.dedup_until:
            self.seen = {t: dict.fromkeys(list(d)[-QOS_DEPTH:]) for t, d in self.seen.items() if t in self.durable}
            self.capped = True
        elif self.capped and len(seen) > QOS_DEPTH:
            del seen[next(iter(seen))]
        return False


# ------------------------------------------------------------------- CDR helpers (no rclpy)

def _cdr_layout(raw) -> tuple[str, int]:
    """(struct byte-order char, max alignment) from the 4-byte encapsulation header."""
    if len(raw) < 4:
        raise ValueError("CDR data shorter than its encapsulation header")
    rep = raw[1] | (raw[0] << 8)
    if rep in (0x0000, 0x0001):      # CDR_BE / CDR_LE (XCDR1): 8-byte types align to 8
        return ("<" if rep == 0x0001 else ">"), 8
    if rep in (0x0006, 0x0007):      # CDR2_BE / CDR2_LE (plain XCDR2): max alignment 4
        return ("<" if rep == 0x0007 else ">"), 4
    raise ValueError(f"unsupported CDR representation 0x{rep:04x}")


def stamp_ns_from_cdr(raw) -> int:
    """Header stamp (or Clock value) of a serialized message whose first field is a Time."""
    order, _ = _cdr_layout(raw)
    if len(raw) < 12:
        raise ValueError("CDR data too short for a time stamp")
    sec, nsec = struct.unpack_from(order + "iI", raw, 4)
    return sec * 1_000_000_000 + nsec


def plant_state_seq_end(raw) -> tuple[int, bool]:
    """``(seq, end_of_run)`` of a serialized bike_msgs/PlantState, read in place.

    Layout (PlantState.msg): header{stamp{int32, uint32}, string frame_id}, uint64 seq,
    uint32 batch_periods, float64 control_period_s, string machine, string backend,
    bool measured_by_drive, bool end_of_run.
    """
    order, maxalign = _cdr_layout(raw)
    body = memoryview(raw)[4:]
    pos = 8

    def align(p, n):
        n = min(n, maxalign)
        return (p + n - 1) // n * n

    def skip_string(p):
        p = align(p, 4)
        (n,) = struct.unpack_from(order + "I", body, p)
        return p + 4 + n

    pos = skip_string(pos)              # header.frame_id
    pos = align(pos, 8)
    (seq,) = struct.unpack_from(order + "Q", body, pos)
    pos += 8
    pos = align(pos, 4) + 4             # batch_periods
    pos = align(pos, 8) + 8             # control_period_s
    pos = skip_string(pos)              # machine
    pos = skip_string(pos)              # backend
    pos += 1                            # measured_by_drive
    if pos >= len(body):
        raise ValueError("PlantState data truncated")
    return int(seq), body[pos] != 0


def plant_state_end_of_run(raw) -> bool:
    """The ``end_of_run`` flag of a serialized bike_msgs/PlantState."""
    return plant_state_seq_end(raw)[1]


# ------------------------------------------------------------------- typestore (no rclpy)

def bike_msgs_msg_dir() -> pathlib.Path:
    from ament_index_python.packages import get_package_share_directory
    return pathlib.Path(get_package_share_directory("bike_msgs")) / "msg"


def build_typestore(msg_dir: str | os.PathLike | None = None):
    """rosbags typestore: ROS 2 Jazzy standard types + bike_msgs from the installed .msg files."""
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    typestore = get_typestore(Stores.ROS2_JAZZY)
    msg_dir = pathlib.Path(msg_dir) if msg_dir else bike_msgs_msg_dir()
    types = {}
    files = sorted(glob.glob(str(msg_dir / "*.msg")))
    if not files:
        raise SetupError(f"no bike_msgs .msg files in {msg_dir}")
    for path in files:
        name = f"bike_msgs/msg/{pathlib.Path(path).stem}"
        types.update(get_types_from_msg(pathlib.Path(path).read_text(), name))
    typestore.register(types)
    return typestore


def default_bag_name() -> str:
    return "session_" + _dt.datetime.now(_dt.timezone.utc).strftime("%Y%m%dT%H%M%S_%fZ")


def _rosbags_qos(latched: bool, durable: bool | None = None):
    """The offered QoS a topic's bag connection records (``durable``: transient_local, default
    ``latched``). rosbag2 records what the publishers offered, and ``ros2 bag play`` offers it
    again (rosbag2_storage qos.cpp, adapt_offer_to_recorded_offers): a transient_local topic
    recorded as volatile replays without the history a late subscriber gets live."""
    from rosbags.interfaces import (Qos, QosDurability, QosHistory, QosLiveliness, QosReliability,
                                    QosTime)
    zero = QosTime(0, 0)
    durable = latched if durable is None else durable
    return Qos(QosHistory.KEEP_LAST, QOS_DEPTH if not latched else 1, QosReliability.RELIABLE,
               QosDurability.TRANSIENT_LOCAL if durable else QosDurability.VOLATILE,
               zero, zero, QosLiveliness.AUTOMATIC, zero, False)


def new_writer(path: pathlib.Path, storage: str):
    """A rosbags Writer of a rosbag2 format 9 bag (Jazzy) whose MCAP channels carry the
    ``topic_type_hash`` metadata entry besides ``offered_qos_profiles``, as rosbag2 writes
    them: its MCAP reader takes a topic's type_description_hash from there (rosbag2_storage_mcap
    mcap_storage.cpp, create_topic / read_metadata), e.g. for ``ros2 bag info`` of the .mcap
    alone or ``ros2 bag reindex``; rosbags wrote only the QoS, so the hash read back empty."""
    from rosbags.rosbag2 import StoragePlugin, Writer

    plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
    writer = Writer(path, version=9, storage_plugin=plugin)
    if storage == "mcap":
        writer.STORAGE_PLUGINS = {**Writer.STORAGE_PLUGINS, StoragePlugin.MCAP: _mcap_storage_class()}
    return writer


def _mcap_storage_class():
    from io import BytesIO

    from rosbags.rosbag2 import storage_mcap as sm

    if not all(hasattr(sm, name) for name in ("McapWriter", "Channel", "write_string", "write_channel")):
        raise SetupError("this rosbags version does not expose the MCAP channel writer the recorder needs "
                         "(tested with the version pinned in constraints.txt)")

    class McapStorage(sm.McapWriter):
        """rosbags' MCAP storage (the pinned version), its Channel records with the type hash."""

        def add_connection(self, connection, offered_qos_profiles: str) -> None:
            metadata = BytesIO()
            for key, value in (("offered_qos_profiles", offered_qos_profiles),
                               ("topic_type_hash", connection.digest or "")):
                sm.write_string(metadata, key)
                sm.write_string(metadata, value)
            channel = sm.Channel(connection.id, connection.msgtype, connection.topic,
                                 connection.ext.serialization_format, metadata.getvalue())
            self.channels.append(channel)
            self.channel_stats[connection.id] = 0
            sm.write_channel(self.chunk.bio, channel, self.schemas)

    return McapStorage


class BagSink:
    """The rosbags writer with one connection per recorded topic (no rclpy).

    rosbags writes an MCAP chunk only when it reaches 1 MiB and commits sqlite3 only at
    close, i.e. minutes of data would die with the process; :meth:`flush` forces both out
    (through the storage objects of the pinned rosbags version, checked at open)."""

    def __init__(self, path: pathlib.Path, storage: str, typestore, topics: list[tuple[str, str, bool, bool]],
                 flush_period_s: float = 0.5, durable: Iterable[str] = ()):
        if storage not in STORAGES:
            raise SetupError(f"storage must be one of {', '.join(STORAGES)}, got {storage!r}")
        if path.exists():
            raise SetupError(f"bag {path} already exists; choose another bag_name or record_dir")
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise SetupError(f"cannot create record_dir {path.parent}: {exc.strerror}") from None
        self.path = path
        self.writer = new_writer(path, storage)
        try:
            self.writer.open()
        except Exception as exc:  # noqa: BLE001 - rosbags raises several kinds
            raise SetupError(f"cannot open bag {path}: {exc}") from None
        self.connections = {}
        durable = set(durable)      # not latched, but offered transient_local (PREFER_LATCHED)
        for topic, msgtype, _has_header, latched in topics:
            qos = _rosbags_qos(latched, latched or topic in durable)
            self.connections[topic] = self.writer.add_connection(
                topic, msgtype, typestore=typestore, offered_qos_profiles=[qos])
        self.counts = {topic: 0 for topic, *_ in topics}
        self.closed = False
        self.storage = storage
        st = self.writer.storage
        needed = ("close_chunk", "chunk", "bio") if storage == "mcap" else ("conn",)
        if not all(hasattr(st, name) for name in needed):
            self.writer.abort()
            raise SetupError("this rosbags version does not expose the storage flush the recorder needs "
                             "(tested with the version pinned in constraints.txt)")
        if not flush_period_s > 0:
            raise SetupError(f"flush_period_s must be > 0, got {flush_period_s!r}")
        self.flush_ns = int(flush_period_s * 1e9)
        self.flush_wall_s = float(flush_period_s)
        self.last_flush_ns = None
        self.last_flush_wall = time.monotonic()
        self.flushes = 0
        self.dirty = False

    def write(self, topic: str, t_ns: int, data) -> None:
        t_ns = max(int(t_ns), 0)
        self.writer.write(self.connections[topic], t_ns, bytes(data))
        self.counts[topic] += 1
        self.dirty = True
        if self.last_flush_ns is None:
            self.last_flush_ns = t_ns
        if t_ns - self.last_flush_ns >= self.flush_ns or time.monotonic() - self.last_flush_wall >= self.flush_wall_s:
            self.flush(t_ns)

    def flush(self, t_ns: int | None = None) -> None:
        """Make everything written so far survive a kill -9 (and a power cut: fsync)."""
        self.last_flush_wall = time.monotonic()
        if t_ns is not None:
            self.last_flush_ns = t_ns
        if self.closed or not self.dirty:
            return
        st = self.writer.storage
        if self.storage == "mcap":
            if st.chunk.msgs:
                st.close_chunk()
            st.bio.flush()
            os.fsync(st.bio.fileno())
        else:
            st.conn.commit()
        self.dirty = False
        self.flushes += 1

    def close(self) -> None:
        if not self.closed:
            self.closed = True
            self.writer.close()


# ------------------------------------------------------------------- node

def _ros_type(msgtype: str):
    pkg, sub, name = msgtype.split("/")
    return getattr(importlib.import_module(f"{pkg}.{sub}"), name)


def _make_node_class():
    from rclpy.node import Node
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

    from bike_plant.loop import take_sim_time_from_messages

    class RecorderNode(Node):
        def __init__(self, carry=None, **kwargs):
            """``carry``: the recorder this one takes over from (_hand_over): its bag goes on."""
            super().__init__("recorder", **kwargs)
            take_sim_time_from_messages(self)
            record_dir = self.declare_parameter("record_dir", ".").value
            bag_name = self.declare_parameter("bag_name", "").value or default_bag_name()
            storage = self.declare_parameter("storage", "mcap").value
            self.stop_on_end_of_run = bool(self.declare_parameter("stop_on_end_of_run", False).value)
            flush_period_s = self.declare_parameter("flush_period_s", 0.5).value
            self.writers_wait_s = self.declare_parameter("writers_wait_s", WRITERS_WAIT_S).value
            if "/" in bag_name or bag_name in (".", ".."):
                raise SetupError(f"bag_name must be a plain name, got {bag_name!r}")
            path = pathlib.Path(os.path.expanduser(record_dir or ".")).resolve() / bag_name

            topics = []
            for rel, msgtype, has_header in TOPICS:
                full = self.resolve_topic_name(rel)
                topics.append((full, msgtype, has_header, rel in LATCHED_TOPICS))
            try:
                typestore = build_typestore()
            except SetupError:
                raise
            except Exception as exc:  # noqa: BLE001
                raise SetupError(f"cannot load bike_msgs definitions: {exc}") from None
            for name, value in (("flush_period_s", flush_period_s),
                                ("writers_wait_s", self.writers_wait_s)):
                if not isinstance(value, (int, float)) or isinstance(value, bool) or not 0 <= value < 1e6:
                    raise SetupError(f"{name} must be a number of seconds >= 0, got {value!r}")
            # the topics our own publishers offer transient_local (session, drive emulator)
            durable = {self.resolve_topic_name(t) for t in PREFER_LATCHED}
            self.sink = carry.sink if carry is not None else BagSink(path, storage, typestore, topics,
                                                                     float(flush_period_s), durable)
            # what a new run's bag is made with (a restarted plant: _next_run_bag)
            self._bag_args = (storage, typestore, topics, float(flush_period_s), durable)
            self.bag_paths = [path]           # the first, then one per restarted plant's run
            self.run_seq_max = -1             # highest PlantState seq of the run being written
            self._latched_raw: dict[str, bytes] = {}
            # Command copies dropped since the last PlantState (bounded like the window itself)
            self._dropped_since_state: collections.deque = collections.deque(maxlen=RESENT_COMMAND_WINDOW)
            # also flush while nothing arrives (a paused or stalled run)
            self._flush_timer = self.create_timer(float(flush_period_s), self._flush_idle)
            self.latest_clock_ns = 0
            self.last_msg_wall = time.monotonic()
            self.heard_any = False               # any message yet (check_deaf_start)
            from bike_plant.shm_ports import StalePortWatch
            self.deaf_watch = StalePortWatch(since=self.last_msg_wall)
            from bike_plant.shm_ports import StalePeerWatch
            self.peer_watch = StalePeerWatch(since=self.last_msg_wall)    # heard some (check_stale_peers)
            self.handover = HandOverLog(durable | {self.resolve_topic_name(t) for t in LATCHED_TOPICS})
            self.fresh_ports_wanted = False
            self.end_of_run_seen = False
            self.bad_stamps = 0
            # lockstep: a plant that waits for an answer re-publishes its pending PlantState and
            # /clock (republish_s); the copy carries nothing new and would break bag identity
            self.republished_dropped = 0
            self._last_raw: dict[str, bytes] = {}
            # the session re-sends the Commands in force (same stamps and values) when the plant
            # re-publishes: whether it does depends on discovery timing, not on the run
            self.resent_commands_dropped = 0
            self._recent_commands: collections.deque[bytes] = collections.deque(maxlen=RESENT_COMMAND_WINDOW)
            self.command_topic = self.resolve_topic_name("command")
            self.info_topic = self.resolve_topic_name("session_info")
            # the session's topics that have delivered a message: a reader counts its writer
            # matched before that writer has matched it and sent its history (discovery is one
            # way at a time), and a recorder stopped in between lost the history (CI, 2026-12-07)
            self._session_heard: set[str] = set()
            self.plant_state_topic = self.resolve_topic_name("plant_state")
            self.clock_topic = "/clock"
            # topics whose copies arrive right after the original (one seq per batch); the
            # battery's only at seq 0, for a reader that matched late (the plant's
            # _resend_seq_0_to_late_readers), none other is ever byte-identical (its stamp)
            self._copied_topics = {self.clock_topic, self.plant_state_topic,
                                   self.resolve_topic_name("drive_command"),
                                   self.resolve_topic_name("controller_status"),
                                   self.resolve_topic_name("battery")}
            self.subs = {}
            self._to_volatile: set[str] = set()
            prefer = {self.resolve_topic_name(t) for t in PREFER_LATCHED}
            self._specs = {}
            # topics a volatile publisher made volatile stay so in a hand-over's new node (_hand_over)
            self._downgraded: set[str] = set(carry._downgraded) if carry is not None else set()
            for full, msgtype, has_header, latched in topics:
                self._specs[full] = (msgtype, has_header, latched)
                self._subscribe(full, transient_local=(latched or full in prefer) and full not in self._downgraded)
            self._downgrade_timer = self.create_timer(0.2, self._apply_downgrades)
            from std_msgs.msg import UInt64
            self._progress_msg = UInt64()
            # transient_local: a plant that (re)matches late still learns where the recorder is
            from diagnostic_msgs.msg import DiagnosticArray
            self.pub_diag = self.create_publisher(DiagnosticArray, "/diagnostics", 10)   # check_stale_peers
            self.pub_progress = self.create_publisher(
                UInt64, "recorder_progress",
                QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1, reliability=ReliabilityPolicy.RELIABLE,
                           durability=DurabilityPolicy.TRANSIENT_LOCAL))
            self.plant_states_written = 0
            self._pending_progress: int | None = None    # a seq to confirm once the session is matched
            self._writers_matched = False
            self._hold_since: float | None = None
            # every recorded topic is taken straight from one reused wait set (HotWait): the
            # executor's spin_once rebuilt a wait set over the whole node and ran a task per
            # message, ~2/3 of the recorder's CPU, and a recorder slower than the loop holds
            # a lockstep run back (recorder_window_batches). Timers, QoS events and
            # parameter services still go through the executor.
            from rclpy.executors import SingleThreadedExecutor

            from bike_plant.loop import HotWait
            self.executor_ = SingleThreadedExecutor(context=self.context)
            self.executor_.add_node(self)
            self.hot = HotWait(self.executor_, list(self.subs.values()), self.context, logger=self.get_logger())

        def spin(self, timeout_s: float) -> int:
            """Record every message waiting (waiting up to ``timeout_s`` for the first)."""
            return self.hot.spin(timeout_s)

        def _subscribe(self, full: str, transient_local: bool) -> None:
            from rclpy.event_handler import SubscriptionEventCallbacks

            msgtype, has_header, latched = self._specs[full]
            qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1 if latched else QOS_DEPTH,
                             reliability=ReliabilityPolicy.RELIABLE,
                             durability=DurabilityPolicy.TRANSIENT_LOCAL if transient_local else DurabilityPolicy.VOLATILE)
            events = None
            if transient_local and not latched:
                events = SubscriptionEventCallbacks(incompatible_qos=lambda _status, t=full: self._to_volatile.add(t))
            self.subs[full] = self.create_subscription(_ros_type(msgtype), full, self._make_callback(full, has_header),
                                                       qos, raw=True, event_callbacks=events)

        def _apply_downgrades(self) -> None:
            while self._to_volatile:
                full = self._to_volatile.pop()
                self._downgraded.add(full)
                self.get_logger().warning(f"{full}: a volatile publisher appeared; recording it with a volatile "
                                          "subscription (messages sent before it matched are not in the bag)")
                old = self.subs.pop(full)
                self._subscribe(full, transient_local=False)
                self.hot.replace(old, self.subs[full])
                self.destroy_subscription(old)

        def _next_run_bag(self) -> None:
            """A restarted plant's new run: close this bag, open ``<first bag>_runN`` beside it
            and write the latched messages into it again (they are not re-sent)."""
            old = self.sink
            old.close()
            first = self.bag_paths[0]
            n = len(self.bag_paths) + 1
            while first.with_name(f"{first.name}_run{n}").exists():   # never overwrite: the next free name
                n += 1
            path = first.with_name(f"{first.name}_run{n}")
            self.sink = BagSink(path, *self._bag_args)
            self.bag_paths.append(path)
            self.get_logger().warning(
                f"PlantState seq 0 after seq {self.run_seq_max}: the plant restarted; bag {old.path} closed "
                f"({sum(old.counts.values())} messages), the new run goes to {path}")
            print(f"bag: {path}", flush=True)
            self._last_raw.clear()
            self._recent_commands.clear()       # the session sends the new run's Commands from t = 0
            self.latest_clock_ns = 0
            self.run_seq_max = -1
            self.end_of_run_seen = False
            for topic, raw in self._latched_raw.items():
                self.sink.write(topic, 0, raw)
            # Command copies taken since the old run's last state were the new run's Commands
            for t_ns, raw in self._dropped_since_state:
                self.sink.write(self.command_topic, t_ns, raw)
                self._recent_commands.append(raw)
                self.resent_commands_dropped -= 1
            self._dropped_since_state.clear()

        def _make_callback(self, topic: str, has_header: bool):
            is_clock = topic == self.clock_topic
            is_plant = topic == self.plant_state_topic
            copied = topic in self._copied_topics
            is_command = topic == self.command_topic
            recent_commands = self._recent_commands
            latched = self._specs[topic][2]
            session_heard = self._session_heard if topic in (self.command_topic, self.info_topic) else None

            def callback(raw: bytes) -> None:
                self.last_msg_wall = time.monotonic()
                self.heard_any = True
                if session_heard is not None:
                    session_heard.add(topic)
                if self.sink.closed:
                    return
                if topic in self.handover.seen:
                    raw = bytes(raw)
                    if self.handover.again(topic, raw, self.last_msg_wall):
                        return                             # the old participant wrote it (_hand_over)
                t_ns = self.latest_clock_ns
                if has_header:
                    try:
                        t_ns = stamp_ns_from_cdr(raw)
                    except ValueError:
                        self.bad_stamps += 1
                        t_ns = self.latest_clock_ns
                seq = end = None
                if is_plant:
                    try:
                        seq, end = plant_state_seq_end(raw)
                    except (ValueError, struct.error):
                        pass
                    if seq == 0 and not end and self.run_seq_max > 0:
                        self._next_run_bag()
                if copied:
                    raw = bytes(raw)
                    if self._last_raw.get(topic) == raw:        # byte-identical: a re-publication
                        self.republished_dropped += 1
                        return
                    self._last_raw[topic] = raw
                elif is_command:
                    raw = bytes(raw)
                    if raw in recent_commands:                 # byte-identical: sent again
                        self.resent_commands_dropped += 1
                        # a restarted plant's new run may be taken after its Commands (other
                        # writers, no order between topics): held for _next_run_bag
                        self._dropped_since_state.append((t_ns, raw))
                        return
                    recent_commands.append(raw)
                if is_clock:
                    self.latest_clock_ns = max(self.latest_clock_ns, t_ns)
                if latched:
                    if topic not in self._latched_raw:     # said once: a run started before it lacks it
                        self.get_logger().info(f"{topic}: latched message recorded (written again into each "
                                               "new run's bag)")
                    self._latched_raw[topic] = bytes(raw)
                self.sink.write(topic, t_ns, raw)
                if is_plant:
                    if seq is None:
                        return
                    self.run_seq_max = max(self.run_seq_max, seq)
                    self._dropped_since_state.clear()
                    self.plant_states_written += 1
                    if end:
                        self.end_of_run_seen = True
                    # a run's seq 0 at once: a lockstep plant holds seq 1 until it hears it; and this
                    # recorder's first state at once: a plant that gave up on a dead recorder waits for
                    # a restarted one again from its first report (a held plant sends no new states)
                    if end or seq == 0 or self.plant_states_written == 1 \
                            or self.plant_states_written % PROGRESS_EVERY == 0:
                        self._pending_progress = seq
                        self.release_progress()

            return callback

        def unmatched_writers(self) -> list[str]:
            """Recorded topics with a writer not yet matched to this recorder's reader: the
            session's Command and session_info until a message of theirs has come (always
            expected: the session sends its info at start and its Commands at /clock 0, which a
            held plant sends again; one reliable writer delivers in order, so the first message
            heard means its history before it is in), and any topic whose writers the graph lists beyond
            the matched count (the controller's answers: while seq 0 is held the plant re-sends
            it and the controller its answer, so a late match still records them)."""
            out = []
            for topic, sub in self.subs.items():
                matched = sub.get_publisher_count()
                if topic in (self.command_topic, self.info_topic):
                    if matched < 1 or topic not in self._session_heard:
                        out.append(topic)
                elif matched < len(self.get_publishers_info_by_topic(topic)):
                    out.append(topic)
            return out

        def release_progress(self) -> None:
            """Report the pending written seq, held until the graph's writers have matched this
            recorder (``writers_wait_s`` at most, then said once). Called per report and by main()'s
            loop while one is held; graph queries only until the first match."""
            if self._pending_progress is None:
                return
            if not self._writers_matched:
                unmatched = self.unmatched_writers()
                if not unmatched:
                    self._writers_matched = True
                else:
                    now = time.monotonic()
                    if self._hold_since is None:
                        self._hold_since = now
                    if now - self._hold_since < self.writers_wait_s:
                        return
                    self._writers_matched = True        # given up on: said once, not held again
                    self.get_logger().warning(
                        f"the writers of {', '.join(unmatched)} have not matched this recorder (or sent it nothing) in "
                        f"{self.writers_wait_s:g}s: recording on without waiting for them (the bag may lack "
                        "their first messages)")
            self._progress_msg.data = self._pending_progress
            self._pending_progress = None
            self.pub_progress.publish(self._progress_msg)

        def _flush_idle(self) -> None:
            if time.monotonic() - self.sink.last_flush_wall >= self.sink.flush_wall_s:
                self.sink.flush()

        def close(self) -> None:
            self.sink.close()

        def check_deaf_start(self) -> bool:
            """No message at all DEAF_CHECK_S after start-up while a live process writes to a
            deleted segment of this node's shared-memory ports: a recorder restarted after a
            kill -9 on the killed one's port (Fast DDS's stale port, bike_plant.shm_ports),
            deaf for good (the writers' discovery data goes there too). Its bag is still empty,
            so it says so and asks to start over with a new participant on fresh ports (main(),
            once per process). Looked for every shm_ports.DEAF_CHECK_S while nothing is heard."""
            why = "" if self.heard_any else self.deaf_watch.start_over()
            if not why:
                return False
            self.get_logger().warning(
                f"nothing recorded in the {self.deaf_watch.waited_s():.0f}s since start-up: {why}; starting over with a new DDS "
                f"participant on fresh ports (the empty bag {self.sink.path} is made again)")
            self.fresh_ports_wanted = True
            return True

        def check_stale_peers(self) -> bool:
            """Recording, yet a peer still cannot reach this recorder (a recorder restarted after
            a kill -9 whose plant re-opened the killed one's port while the controller, say, did
            not: its data would be missing from the bag for good; shm_ports.StalePeerWatch). Says
            so once (log and WARN diagnostic, naming the writers) and asks main() to hand the bag
            over to a new participant on fresh ports (_hand_over)."""
            if not self.heard_any or self.fresh_ports_wanted or self.peer_watch.finished:
                return False
            from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus

            from bike_plant.loop import say_stale_peer_and_start_over
            return say_stale_peer_and_start_over(
                self, self.peer_watch, lambda text: self.pub_diag.publish(DiagnosticArray(status=[DiagnosticStatus(
                    level=DiagnosticStatus.WARN, name=self.get_fully_qualified_name(), message=text,
                    hardware_id="bike_session")])),
                f" (the bag {self.sink.path} goes on, nothing lost or written twice)")

        def take_over(self, old) -> None:
            """Go on with ``old``'s recording (_hand_over): its bag and bookkeeping; the Commands
            the callbacks hold are added in place. What this node then takes that ``old`` wrote
            is dropped for HANDOVER_DEDUP_S."""
            for name in RECORDING_STATE:
                setattr(self, name, getattr(old, name))
            self._recent_commands.extend(old._recent_commands)
            self._session_heard.update(old._session_heard)
            self.handover.open_window(time.monotonic())

    return RecorderNode


_signals = {"count": 0}


def _on_signal(signum, frame):  # noqa: ARG001
    _signals["count"] += 1


def main(args=None) -> int:
    import rclpy
    from rclpy.signals import SignalHandlerOptions

    rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)
    signal.signal(signal.SIGINT, _on_signal)
    signal.signal(signal.SIGTERM, _on_signal)
    node = None
    rc = 0
    try:
        node_class = _make_node_class()
        node = node_class()
        print(f"bag: {node.bag_paths[0]}", flush=True)
        node.get_logger().info(f"recording {len(node.subs)} topics to {node.bag_paths[0]}")
        while rclpy.ok(context=node.context) and _signals["count"] == 0:
            if node.spin(0.1):
                time.sleep(GATHER_S)
            elif node.check_deaf_start():
                node = _start_over(node_class, node, args)
            if node.check_stale_peers():                  # a look is due every DEAF_CHECK_S, busy or not
                node = _hand_over(node_class, node, args)
            node.release_progress()
            if node.stop_on_end_of_run and node.end_of_run_seen:
                break
        # drain: until end_of_run is recorded or SILENCE_S without messages (a second signal stops now)
        while rclpy.ok(context=node.context) and not node.end_of_run_seen and _signals["count"] < 2:
            if time.monotonic() - node.last_msg_wall > SILENCE_S:
                break
            node.spin(0.05)
        # take what is already queued (trailing status / commands), 0.2 s of quiet at most
        quiet_until = time.monotonic() + 0.2
        while rclpy.ok(context=node.context) and time.monotonic() < quiet_until and _signals["count"] < 2:
            before = node.last_msg_wall
            node.spin(0.05)
            if node.last_msg_wall != before:
                quiet_until = time.monotonic() + 0.2
        counts = {k: v for k, v in node.sink.counts.items() if v}
        node.close()
        dropped = (f", {node.republished_dropped} re-published loop message copies not written"
                   if node.republished_dropped else "")
        if node.resent_commands_dropped:
            dropped += f", {node.resent_commands_dropped} re-sent Command copies not written"
        if node.handover.dropped:
            dropped += f", {node.handover.dropped} messages taken again at the hand-over not written"
        node.get_logger().info(f"bag closed: {node.sink.path} {counts}{dropped}")
    except SetupError as exc:
        print(f"recorder_node: error: {exc}", file=sys.stderr, flush=True)
        rc = 2
    except KeyboardInterrupt:
        if node is not None:
            node.close()
    finally:
        if node is not None:
            try:
                node.close()
            except Exception as exc:  # noqa: BLE001
                print(f"recorder_node: error closing bag: {exc}", file=sys.stderr, flush=True)
                rc = 1
            node.executor_.remove_node(node)
            node.executor_.shutdown()           # see bike_plant.node.run_loop_node
            node.destroy_node()
            if node.context is not rclpy.get_default_context():   # started over (_start_over)
                rclpy.try_shutdown(context=node.context)
        rclpy.try_shutdown()
    return rc


def _start_over(node_class, old, args):
    """A deaf recorder on a stale port (RecorderNode.check_deaf_start): its empty bag is closed
    and removed, and a new node in a new context, on fresh ports, makes it again
    (bike_plant.loop.start_over_on_fresh_ports)."""
    import shutil

    from bike_plant.loop import start_over_on_fresh_ports
    old.close()
    if not any(old.sink.counts.values()):           # nothing recorded: only our own empty bag goes
        shutil.rmtree(old.sink.path, ignore_errors=True)
    node = start_over_on_fresh_ports(node_class, old, args)
    signal.signal(signal.SIGINT, _on_signal)        # rclpy.init of the new context installed its own
    signal.signal(signal.SIGTERM, _on_signal)
    return node


def _hand_over(node_class, old, args):
    """A running recorder that a peer cannot reach (RecorderNode.check_stale_peers) goes on in
    the same bag with a new node in a new context, on fresh ports: the old one records on
    until the new one's readers have matched as many writers (HANDOVER_WAIT_S at most) and
    has taken all that came; the new one then takes its bag over and drops what it takes
    again (its queue since its match, the transient_local history)."""
    import functools

    from bike_plant.loop import HANDOVER_WAIT_S, start_over_on_fresh_ports, wait_for_new_matches

    def overlap(new) -> None:
        late = wait_for_new_matches([(sub, new.subs[t]) for t, sub in old.subs.items()], lambda: old.spin(0.05))
        while old.spin(0.0):
            pass
        if late:
            old.get_logger().warning(f"the new participant's readers of {', '.join(late)} have not matched every "
                                     f"writer in {HANDOVER_WAIT_S:g}s: their messages until they do are not in the bag")
        new.take_over(old)

    old.handover.start(old.subs)                        # every topic remembered while both listen
    node = start_over_on_fresh_ports(functools.partial(node_class, carry=old), old, args, before_leaving=overlap)
    signal.signal(signal.SIGINT, _on_signal)        # rclpy.init of the new context installed its own
    signal.signal(signal.SIGTERM, _on_signal)
    node.get_logger().info(f"recording on into {node.sink.path}")
    return node


if __name__ == "__main__":
    sys.exit(main())

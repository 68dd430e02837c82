"""``./bike bag recover``: turn what survived of a crashed recording into a normal bag.

A recorder that dies (kill -9, power cut) leaves a bag directory without ``metadata.yaml``
(rosbag2 writes it at close), with

- MCAP: the chunks that were complete at the last flush (the recorder closes a chunk at
  least every ``flush_period_s``), then possibly a torn record;
- sqlite3: the transactions committed up to the last flush (plus maybe a hot journal).

Recovery reads only the complete parts (MCAP: records streamed until the first torn one;
sqlite3: a COPY of the database, so SQLite's journal rollback never touches the original)
and writes them with rosbags into a NEW bag next to the damaged one (``BAG.recovered`` by
default). The original is never modified: recovering loses nothing, even when it fails.
Memory stays bounded: messages are streamed, never collected.
"""
from __future__ import annotations

import os
import pathlib
import shutil
import sqlite3
import tempfile

from bike_session.bags import BagError

MAX_RECORD_BYTES = 256 * 2**20       # a hostile length field must not make us allocate GBs


def _opens(bag: pathlib.Path) -> bool:
    """Whether a bag with its metadata.yaml opens: one whose data file was cut short after it
    was closed (a truncated copy) has the metadata but not the file's summary, and is recovered
    like a crashed recording."""
    from bike_session.bags import open_bag

    try:
        open_bag(bag).close()
    except BagError:
        return False
    return True


def _find_data_file(bag: pathlib.Path) -> pathlib.Path:
    if bag.is_file():
        if bag.suffix in (".mcap", ".db3"):
            return bag
        raise BagError("not a bag: expected a bag directory, a .mcap or a .db3 file", bag)
    files = sorted(bag.glob("*.mcap")) + sorted(bag.glob("*.db3"))
    if not files:
        raise BagError("no .mcap or .db3 data file in this directory: nothing to recover", bag)
    if len(files) > 1:
        raise BagError(f"several data files ({', '.join(f.name for f in files)}); recover them one by one", bag)
    return files[0]


class _Out:
    """The new bag, created on the first message (no empty bag is left behind on failure)."""

    def __init__(self, out: pathlib.Path, storage: str):
        self.out = out
        self.storage = storage
        self.writer = None
        self.typestore = None
        self.conns: dict[object, object] = {}
        self.count = 0
        self.counts: dict[str, int] = {}
        self.start_ns = None
        self.end_ns = None

    def _failed(self, exc: Exception) -> BagError:
        # the new bag's error, not the crashed one's: the source readers take any other exception
        # from inside their loop for the torn tail of the recording (a NotADirectoryError of
        # --out was "no complete message survived"; a full disk ended the copy as "recovered")
        return BagError(f"cannot write the recovered bag {self.out} (--out): {type(exc).__name__}: {exc}")

    def _open(self):
        try:
            self._open_writer()
        except BagError:
            raise
        except Exception as exc:  # noqa: BLE001 - OSError, rosbags' WriterError
            raise self._failed(exc) from None

    def _open_writer(self):
        from rosbags.typesys import Stores, get_typestore

        from bike_session.recorder_node import new_writer
        self.writer = new_writer(self.out, self.storage)
        self.writer.open()
        self.typestore = get_typestore(Stores.EMPTY)

    def add(self, key, topic: str, msgtype: str, msgdef: str, qos_text: str | None) -> None:
        from rosbags.typesys import get_types_from_msg

        from bike_session.recorder_node import _rosbags_qos

        if self.writer is None:
            self._open()
        try:
            types = get_types_from_msg(msgdef, msgtype)
        except Exception as exc:  # noqa: BLE001 - rosbags raises several kinds
            raise BagError(f"embedded definition of {msgtype} ({topic}) cannot be parsed: {exc}") from None
        self.typestore.register({k: v for k, v in types.items() if k not in self.typestore.types})
        # the crashed bag's own offered QoS, as rosbag2 would replay it; unreadable: a guess
        # from its durability (latched: depth 1)
        try:
            from rosbags.rosbag2.metadata import parse_qos
            qos = parse_qos(qos_text or "")
        except Exception:  # noqa: BLE001 - ReaderError, a malformed or foreign entry
            qos = []
        if not qos:
            qos = [_rosbags_qos("transient_local" in (qos_text or ""))]
        try:
            self.conns[key] = self.writer.add_connection(topic, msgtype, typestore=self.typestore,
                                                         offered_qos_profiles=qos)
        except Exception as exc:  # noqa: BLE001
            raise self._failed(exc) from None
        self.counts.setdefault(topic, 0)

    def write(self, key, t_ns: int, data: bytes) -> None:
        conn = self.conns[key]
        try:
            self.writer.write(conn, int(t_ns), data)
        except Exception as exc:  # noqa: BLE001
            raise self._failed(exc) from None
        self.count += 1
        self.counts[conn.topic] += 1
        self.start_ns = t_ns if self.start_ns is None else min(self.start_ns, t_ns)
        self.end_ns = t_ns if self.end_ns is None else max(self.end_ns, t_ns)

    def finish(self, recovered_from: pathlib.Path, note: str) -> None:
        if self.writer is None:
            return
        self.writer.set_custom_data("bike.recovered_from", str(recovered_from))
        self.writer.set_custom_data("bike.recovery", note)
        try:
            self.writer.close()
        except Exception as exc:  # noqa: BLE001
            raise self._failed(exc) from None

    def abort(self) -> None:
        if self.writer is not None:
            try:
                self.writer.abort()
            finally:
                shutil.rmtree(self.out, ignore_errors=True)


def _recover_mcap(src: pathlib.Path, out: _Out) -> str:
    """Stream Schema / Channel / Message records until the first torn or invalid one."""
    from mcap.records import Channel, Message, Schema
    from mcap.stream_reader import StreamReader

    from bike_session.bags import mcap_chunk_problem

    schemas = {}
    channels = {}
    stop = "end of file"
    # a chunk that would inflate past its bound ends the recording there, as a torn record does
    problem = mcap_chunk_problem(src)
    with open(src, "rb") as fh:
        try:
            stream = fh if problem is None else _UpTo(fh, problem[0])
            reader = StreamReader(stream, skip_magic=False, emit_chunks=False, validate_crcs=True,
                                  record_size_limit=MAX_RECORD_BYTES)
            for rec in reader.records:
                if isinstance(rec, Schema):
                    schemas[rec.id] = rec
                elif isinstance(rec, Channel) and rec.id in channels:
                    # a whole file's summary repeats its channels (metadata.yaml lost, or a .mcap alone)
                    if rec.topic != channels[rec.id].topic:
                        raise BagError(f"channel {rec.id} is {rec.topic!r} here and {channels[rec.id].topic!r} "
                                       f"before: not one recording", src)
                elif isinstance(rec, Channel):
                    schema = schemas.get(rec.schema_id)
                    if schema is None or schema.encoding != "ros2msg" or rec.message_encoding != "cdr":
                        raise BagError(f"channel {rec.topic!r} has no ros2msg schema: not a ROS 2 bag", src)
                    channels[rec.id] = rec
                    out.add(rec.id, rec.topic, schema.name, schema.data.decode("utf-8", "replace"),
                            rec.metadata.get("offered_qos_profiles"))
                elif isinstance(rec, Message):
                    if rec.channel_id not in channels:
                        raise BagError(f"message on unknown channel {rec.channel_id}", src)
                    out.write(rec.channel_id, rec.log_time, rec.data)
        except BagError:
            raise
        except Exception as exc:  # noqa: BLE001 - McapError, EndOfFile, struct.error, ... from a torn tail
            # the torn tail of a killed writer ends up here; everything before it is kept
            from bike_session.bags import _reason
            name, text = type(exc).__name__, str(exc).strip()
            if isinstance(exc, MemoryError):
                what = _reason(exc)
            elif text:
                what = f"{name}: {text}"
            else:
                # mcap's EndOfFile carries no text: it read "(EndOfFile: )"
                what = f"{name}: the data ends inside it" if name == "EndOfFile" else name
            stop = f"stopped at a torn or invalid record ({what})"
    if problem is not None:
        stop = f"stopped before an invalid chunk ({problem[1]})"
    return stop


class _UpTo:
    """The file ``fh`` read as if it ended at byte ``end``."""

    def __init__(self, fh, end: int):
        self.fh, self.end = fh, end

    def read(self, n: int = -1) -> bytes:
        left = max(self.end - self.fh.tell(), 0)
        return self.fh.read(left if n is None or n < 0 else min(n, left))


def _recover_sqlite3(src: pathlib.Path, out: _Out) -> str:
    with tempfile.TemporaryDirectory(prefix="bike-recover-") as tmp:
        copy = pathlib.Path(tmp) / src.name
        shutil.copy2(src, copy)
        for suffix in ("-journal", "-wal"):
            side = src.with_name(src.name + suffix)
            if side.exists():
                shutil.copy2(side, copy.with_name(copy.name + suffix))
        try:
            conn = sqlite3.connect(f"file:{copy}", uri=True)
            defs = {t: d for t, d in conn.execute(
                "SELECT topic_type, encoded_message_definition FROM message_definitions")}
            for tid, name, msgtype, qos in conn.execute(
                    "SELECT id, name, type, offered_qos_profiles FROM topics ORDER BY id"):
                if msgtype not in defs:
                    raise BagError(f"topic {name!r}: no embedded definition of {msgtype}", src)
                out.add(tid, name, msgtype, defs[msgtype], qos)
            for tid, t_ns, data in conn.execute("SELECT topic_id, timestamp, data FROM messages ORDER BY id"):
                if tid not in out.conns:
                    raise BagError(f"message on unknown topic id {tid}", src)
                out.write(tid, t_ns, bytes(data))
            conn.close()
        except sqlite3.DatabaseError as exc:
            raise BagError(f"not a readable rosbag2 sqlite3 database: {exc}", src) from None
    return "committed transactions"


def recover(bag: str | os.PathLike, out: str | os.PathLike | None = None) -> dict:
    """Recover the bag directory (or data file) ``bag`` into ``out`` (default ``BAG.recovered``).

    Returns a summary dict: out, messages, topics (counts), start_ns, end_ns, stop (why
    reading ended). Raises :class:`BagError` with one clear reason; on error nothing is
    written and the original is untouched."""
    bag = pathlib.Path(bag)
    if not bag.exists():
        raise BagError("no such bag (path does not exist)", bag)
    if bag.is_dir() and (bag / "metadata.yaml").is_file() and _opens(bag):
        raise BagError("this bag was closed properly (metadata.yaml present): nothing to recover; "
                       "read it with ./bike report", bag)
    src = _find_data_file(bag)
    base = bag if bag.is_dir() else bag.with_suffix("")
    out_path = pathlib.Path(out) if out is not None else base.with_name(base.name + ".recovered")
    if out_path.exists():
        raise BagError(f"output {out_path} already exists; choose another with --out", bag)
    storage = "mcap" if src.suffix == ".mcap" else "sqlite3"
    sink = _Out(out_path, storage)
    try:
        stop = _recover_mcap(src, sink) if storage == "mcap" else _recover_sqlite3(src, sink)
        if sink.count == 0:
            raise BagError(f"no complete message survived ({stop})", bag)
        sink.finish(src, stop)
    except BaseException:
        sink.abort()
        raise
    return {"out": str(out_path), "messages": sink.count, "topics": dict(sink.counts),
            "start_ns": sink.start_ns, "end_ns": sink.end_ns, "stop": stop, "storage": storage}


def main(argv: list[str]) -> int:
    import argparse
    import sys

    ap = argparse.ArgumentParser(prog="bike bag recover", description=__doc__.split("\n\n")[0])
    ap.add_argument("bag", help="the crashed bag directory (or its .mcap / .db3 file)")
    ap.add_argument("--out", help="where to write the recovered bag (default: BAG.recovered)")
    opts = ap.parse_args(argv)
    try:
        res = recover(opts.bag, opts.out)
    except BagError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    span = (res["end_ns"] - res["start_ns"]) * 1e-9
    print(f"recovered {res['messages']} messages, {span:.3f} s of sim time, into {res['out']}")
    for topic, n in sorted(res["topics"].items()):
        print(f"  {topic}: {n}")
    print(f"  ({res['storage']}: {res['stop']})")
    return 0

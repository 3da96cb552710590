"""Sequential reader for unindexed ROS 1 bags (format 2.0), the bag a killed recorder leaves.

``rosbag record`` writes ``NAME.bag.active``: the 4 KiB bag header (with ``index_pos``
0 until the end), then chunk records, each followed by its index data records. Only
when recording stops cleanly does it append the index (connection and chunk-info
records), set ``index_pos`` and rename the file to ``NAME.bag``. A recorder killed by a
power cut, a flat battery or a crash leaves the ``.active`` file: no index, and usually
a last record cut short. The ``rosbags`` library refuses such a bag ("Bag is not
indexed, reindex before reading."); ROS's fix is ``rosbag reindex``.

:class:`UnindexedBag1Reader` walks the records from the start instead, in the file's
order, and builds the index in memory:

* a chunk record (op 5) is decompressed (``none``, ``bz2``, ``lz4``) and its connection
  (op 7) and message data (op 2) records are collected;
* connection and message records outside a chunk are taken as well: the records of a
  chunk that was still open when the recorder stopped (its header carries the
  placeholder size 0, or the sizes of a chunk whose data is cut short) follow each other
  in the file when the chunk is uncompressed;
* index data (op 4), chunk info (op 6) and unknown records are skipped;
* the first record that does not fit in the file (or cannot be parsed) ends the walk:
  every complete message before it is kept, and its bytes up to the end of the file
  are counted as the lost tail (:attr:`ScanReport.tail_bytes`).

Messages are then served like rosbags' indexed reader serves them (same connections,
same order: bag time, then the order of the requested connections, then file order),
and deserialized with a rosbags type store built from the bags' message definitions
(as rosbags' ``AnyReader`` does), so the import of an unindexed bag writes the same log
as the import of the same bag indexed.
"""

from __future__ import annotations

import bz2
import struct
from collections.abc import Collection, Iterator
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType
from typing import Any, BinaryIO

import numpy as np

from sonarloc.errors import SonarlocError

OP_MSGDATA = 2
OP_BAGHEADER = 3
OP_IDXDATA = 4
OP_CHUNK = 5
OP_CHUNKINFO = 6
OP_CONNECTION = 7

MAGIC = b"#ROSBAG V2.0\n"
_U32 = struct.Struct("<I")
_TIME = struct.Struct("<II")


class BagScanError(SonarlocError):
    """The file is not a ROS 1 bag v2.0, or a record in it cannot be used."""


@dataclass
class ScanReport:
    """What the sequential walk found.

    Attributes
    ----------
    size_bytes : size of the file, bytes.
    index_pos : the bag header's ``index_pos`` (0: never indexed).
    chunks : chunk records read completely.
    messages : message data records kept.
    connections : connection records (distinct ids).
    tail_bytes : bytes from the first incomplete or unreadable record to the end of the
        file, not read (0: the walk reached the end cleanly).
    tail_pos : file offset of that record, bytes (None when ``tail_bytes`` is 0).
    tail_what : what that record was (``"chunk (bz2)"``, ``"message data"``, ...).
    inline_messages : messages read outside a complete chunk (from a chunk still open
        when the recorder stopped).
    orphan_messages : messages of a connection id that no connection record defines
        (dropped).
    """

    size_bytes: int = 0
    index_pos: int = 0
    chunks: int = 0
    messages: int = 0
    connections: int = 0
    tail_bytes: int = 0
    tail_pos: int | None = None
    tail_what: str = ""
    inline_messages: int = 0
    orphan_messages: int = 0

    def summary(self) -> str:
        """One line for the import summary."""
        text = (f"unindexed ROS 1 bag (index_pos {self.index_pos}) read sequentially: "
                f"{self.messages} messages in {self.chunks} chunks")
        if self.inline_messages:
            text += f" + {self.inline_messages} from an unfinished chunk"
        if self.tail_bytes:
            text += (f"; the last {self.tail_bytes} bytes (from byte {self.tail_pos}, "
                     f"{self.tail_what}) were a truncated record and are lost")
        else:
            text += "; no truncated record at the end"
        if self.orphan_messages:
            text += f"; {self.orphan_messages} messages without a connection record dropped"
        return text


def _parse_header(buf: bytes | memoryview) -> dict[str, bytes] | None:
    """The ``name=value`` fields of a record header, or None when they do not parse."""
    fields: dict[str, bytes] = {}
    pos, end = 0, len(buf)
    while pos < end:
        if pos + 4 > end:
            return None
        (n,) = _U32.unpack_from(buf, pos)
        pos += 4
        if n > end - pos:
            return None
        field = bytes(buf[pos:pos + n])
        pos += n
        name, sep, value = field.partition(b"=")
        if not sep:
            return None
        try:
            fields[name.decode("ascii")] = value
        except UnicodeDecodeError:
            return None
    return fields


def _op(fields: dict[str, bytes]) -> int | None:
    op = fields.get("op")
    return op[0] if op is not None and len(op) == 1 else None


def _u32(fields: dict[str, bytes], name: str) -> int | None:
    v = fields.get(name)
    return _U32.unpack(v)[0] if v is not None and len(v) == 4 else None


def _time_ns(fields: dict[str, bytes]) -> int | None:
    v = fields.get("time")
    if v is None or len(v) != 8:
        return None
    sec, nsec = _TIME.unpack(v)
    return sec * 1_000_000_000 + nsec


def _text(fields: dict[str, bytes], name: str) -> str | None:
    v = fields.get(name)
    return v.decode("utf-8", errors="replace") if v is not None else None


def _normalize_topic(name: str) -> str:
    """Topic name with repeated slashes collapsed (as rosbags' reader does)."""
    return ("/" if name.startswith("/") else "") + "/".join(p for p in name.split("/") if p)


def _decompress(data: bytes, compression: str) -> bytes:
    if compression == "none":
        return data
    if compression == "bz2":
        return bz2.decompress(data)
    if compression == "lz4":
        try:
            import lz4.frame
        except ImportError as err:  # pragma: no cover - lz4 comes with rosbags
            raise BagScanError(
                "the bag has lz4-compressed chunks: install the `lz4` package "
                "(pip install lz4), or reindex the bag with `rosbag reindex`") from err
        out: bytes = lz4.frame.decompress(data)
        return out
    raise BagScanError(f"chunk compression {compression!r} is not supported "
                       "(ROS 1 bags use none, bz2 or lz4)")


@dataclass
class _Conn:
    id: int
    topic: str
    msgtype_ros1: str
    md5sum: str
    msgdef: str
    callerid: str | None
    latching: int | None


class UnindexedBag1Reader:
    """Read a ROS 1 bag v2.0 without its index, walking the records from the start.

    Duck-typed like rosbags' ``AnyReader`` for what sonarloc uses: ``connections``,
    ``messages(connections)``, ``deserialize(raw, msgtype)``, a context manager; plus
    :attr:`report` (a :class:`ScanReport`).

    Parameters
    ----------
    path : the bag file (``NAME.bag.active`` or ``NAME.bag``).
    default_typestore : rosbags type store used when the bag has no connection records
        carrying message definitions.
    """

    def __init__(self, path: str | Path, default_typestore: Any = None) -> None:
        self.path = Path(path)
        self.default_typestore = default_typestore
        self.report = ScanReport()
        self.connections: list[Any] = []
        self.typestore: Any = None
        self._file: BinaryIO | None = None
        self._chunks: list[tuple[int, int, str]] = []   # (data pos, data len, compression)
        self._cache: tuple[int, bytes] = (-2, b"")
        # per message: bag time ns, chunk index (-1: outside a chunk), offset of the data
        # (in the decompressed chunk, or in the file), data length, connection id
        self._msgs = np.zeros((0, 5), dtype=np.int64)

    # ------------------------------------------------------------------ walk
    def open(self) -> None:
        """Walk the file and build the in-memory index and the type store."""
        if self._file is not None:
            raise BagScanError(f"bag {self.path} is open already")
        try:
            self._file = self.path.open("rb")
        except OSError as err:
            raise BagScanError(f"cannot open: {err.strerror}") from err
        try:
            conns = self._walk(self._file)
            self._finish(conns)
        except BaseException:
            self.close()
            raise

    def _walk(self, f: BinaryIO) -> dict[int, _Conn]:
        rep = self.report
        f.seek(0, 2)
        size = rep.size_bytes = f.tell()
        f.seek(0)
        magic = f.readline(64)
        if magic != MAGIC:
            if magic.startswith(b"#ROSBAG V") or magic.startswith(b"#ROSRECORD V"):
                version = magic.strip().decode(errors="replace")
                raise BagScanError(f"bag version {version!r} is not supported "
                                   "(ROS 1 bags are #ROSBAG V2.0)")
            raise BagScanError("not a ROS 1 bag (no '#ROSBAG V2.0' line)")
        pos = len(MAGIC)
        conns: dict[int, _Conn] = {}
        rows: list[tuple[int, int, int, int, int]] = []
        first = True
        while pos < size:
            rec = self._read_record_head(f, pos, size)
            if rec is None:
                self._tail(pos, "unreadable record header")
                break
            fields, data_pos, data_len = rec
            op = _op(fields)
            if first:
                if op != OP_BAGHEADER:
                    raise BagScanError(f"the first record is not a bag header "
                                       f"(op {op}); not a ROS 1 bag v2.0")
                first = False
            complete = data_pos + data_len <= size
            if op == OP_CHUNK:
                compression = _text(fields, "compression") or "none"
                if data_len == 0:
                    # the placeholder header of a chunk still open when the recorder
                    # stopped: an uncompressed one's records follow it
                    pos = data_pos
                    continue
                if not complete:
                    if compression == "none":
                        # the records of a cut uncompressed chunk follow each other:
                        # keep walking them one by one
                        pos = data_pos
                        continue
                    self._tail(pos, f"chunk ({compression})")
                    break
                f.seek(data_pos)
                raw = f.read(data_len)
                try:
                    data = _decompress(raw, compression)
                except (OSError, ValueError, EOFError, RuntimeError):
                    self._tail(pos, f"chunk ({compression}) that does not decompress")
                    break
                index = len(self._chunks)
                self._chunks.append((data_pos, data_len, compression))
                bad = self._walk_chunk(data, index, conns, rows)
                if bad is not None:
                    self._tail(pos, f"chunk ({compression}) with a damaged record at "
                                    f"offset {bad}")
                    break
                rep.chunks += 1
            elif op == OP_BAGHEADER:
                if not complete:
                    self._tail(pos, "bag header")
                    break
                v = fields.get("index_pos")
                rep.index_pos = struct.unpack("<Q", v)[0] if v is not None and len(v) == 8 else 0
            elif op == OP_CONNECTION:
                if not complete:
                    self._tail(pos, "connection")
                    break
                f.seek(data_pos)
                if not self._add_conn(fields, f.read(data_len), conns):
                    self._tail(pos, "damaged connection")
                    break
            elif op == OP_MSGDATA:
                if not complete:
                    self._tail(pos, "message data")
                    break
                conn, t = _u32(fields, "conn"), _time_ns(fields)
                if conn is None or t is None:
                    self._tail(pos, "damaged message data")
                    break
                rows.append((t, -1, data_pos, data_len, conn))
                rep.inline_messages += 1
            elif not complete:
                self._tail(pos, {OP_IDXDATA: "index data, no messages in it",
                                 OP_CHUNKINFO: "chunk info, no messages in it"}
                           .get(op or -1, f"op {op}"))
                break
            pos = data_pos + data_len
        if first:
            raise BagScanError(f"no complete bag header record in its {size} bytes")
        if rows:
            self._msgs = np.array(rows, dtype=np.int64)
        return conns

    def _read_record_head(self, f: BinaryIO, pos: int, size: int
                          ) -> tuple[dict[str, bytes], int, int] | None:
        """(header fields, data position, data length) of the record at ``pos``."""
        if pos + 4 > size:
            return None
        f.seek(pos)
        (hlen,) = _U32.unpack(f.read(4))
        if hlen > size - pos - 8:
            return None
        fields = _parse_header(f.read(hlen))
        if fields is None or _op(fields) is None:
            return None
        (dlen,) = _U32.unpack(f.read(4))
        return fields, pos + 8 + hlen, dlen

    def _walk_chunk(self, data: bytes, index: int, conns: dict[int, _Conn],
                    rows: list[tuple[int, int, int, int, int]]) -> int | None:
        """Collect the connections and messages of a chunk; offset of a bad record or None."""
        view = memoryview(data)
        pos, end = 0, len(data)
        while pos < end:
            if pos + 4 > end:
                return pos
            (hlen,) = _U32.unpack_from(view, pos)
            if hlen > end - pos - 8:
                return pos
            fields = _parse_header(view[pos + 4:pos + 4 + hlen])
            if fields is None:
                return pos
            (dlen,) = _U32.unpack_from(view, pos + 4 + hlen)
            dpos = pos + 8 + hlen
            if dpos + dlen > end:
                return pos
            op = _op(fields)
            if op == OP_MSGDATA:
                conn, t = _u32(fields, "conn"), _time_ns(fields)
                if conn is None or t is None:
                    return pos
                rows.append((t, index, dpos, dlen, conn))
                self.report.messages += 1
            elif op == OP_CONNECTION:
                if not self._add_conn(fields, bytes(view[dpos:dpos + dlen]), conns):
                    return pos
            pos = dpos + dlen
        return None

    def _add_conn(self, fields: dict[str, bytes], data: bytes, conns: dict[int, _Conn]) -> bool:
        cid = _u32(fields, "conn")
        topic = _text(fields, "topic")
        inner = _parse_header(data)
        if cid is None or topic is None or inner is None:
            return False
        if cid in conns:
            return True
        typ, md5 = _text(inner, "type"), _text(inner, "md5sum")
        if typ is None or md5 is None:
            return False
        latching = _text(inner, "latching")
        conns[cid] = _Conn(cid, _normalize_topic(topic), typ, md5,
                           _text(inner, "message_definition") or "",
                           _text(inner, "callerid"),
                           int(latching) if latching not in (None, "") and latching.isdigit()
                           else None)
        return True

    def _tail(self, pos: int, what: str) -> None:
        self.report.tail_pos = pos
        self.report.tail_bytes = self.report.size_bytes - pos
        self.report.tail_what = what

    def _finish(self, conns: dict[int, _Conn]) -> None:
        """rosbags connections and a type store from the message definitions."""
        from rosbags.interfaces import (
            Connection,
            ConnectionExtRosbag1,
            MessageDefinition,
            MessageDefinitionFormat,
        )
        from rosbags.typesys import Stores, get_types_from_msg, get_typestore
        from rosbags.typesys.msg import normalize_msgtype

        if len(self._msgs):
            known = np.isin(self._msgs[:, 4], np.array(sorted(conns), dtype=np.int64))
            self.report.orphan_messages = int((~known).sum())
            self.report.inline_messages -= int((~known & (self._msgs[:, 1] < 0)).sum())
            self.report.messages -= int((~known & (self._msgs[:, 1] >= 0)).sum())
            self._msgs = self._msgs[known]
        self.report.connections = len(conns)
        ids, n = np.unique(self._msgs[:, 4], return_counts=True)
        counts = dict(zip(ids.tolist(), n.tolist(), strict=True))
        out = []
        for cid in sorted(conns):
            c = conns[cid]
            out.append(Connection(
                c.id, c.topic, normalize_msgtype(c.msgtype_ros1),
                MessageDefinition(MessageDefinitionFormat.MSG, c.msgdef), c.md5sum,
                counts.get(cid, 0),
                ConnectionExtRosbag1(c.callerid, c.latching), self))
        self.connections = out
        if not out:
            self.typestore = self.default_typestore or get_typestore(Stores.EMPTY)
            return
        typs: dict[str, Any] = {}
        try:
            for conn in out:
                typs.update(get_types_from_msg(conn.msgdef.data, conn.msgtype))
            store = get_typestore(Stores.EMPTY)
            store.register(typs)
        except Exception as err:
            raise BagScanError(f"a message definition does not parse: "
                               f"{str(err).strip().splitlines()[0] if str(err).strip() else err!r}"
                               ) from err
        for conn in out:
            have = store.generate_msgdef(conn.msgtype)[1]
            if have != conn.digest:
                raise BagScanError(f"message type {conn.msgtype!r} hash mismatch "
                                   f"{have} != {conn.digest}")
        self.typestore = store

    # ------------------------------------------------------------------ read
    def messages(self, connections: Collection[Any] = ()) -> Iterator[tuple[Any, int, bytes]]:
        """(connection, bag time ns, raw message) of the given connections (default all).

        In the order rosbags' indexed reader gives: bag time, then the position of the
        message's connection in ``connections``, then file order.
        """
        if self._file is None:
            raise BagScanError(f"bag {self.path} is not open")
        conns = list(connections) or self.connections
        rank = {c.id: i for i, c in reversed(list(enumerate(conns)))}
        by_id = {c.id: c for c in self.connections}
        m = self._msgs
        if not len(m) or not rank:
            return
        ids = np.array(sorted(rank), dtype=np.int64)
        sel = np.flatnonzero(np.isin(m[:, 4], ids))
        if not len(sel):
            return
        ranks = np.array([rank[i] for i in ids.tolist()], dtype=np.int64)
        sub = m[sel]
        order = np.lexsort((sel, ranks[np.searchsorted(ids, sub[:, 4])], sub[:, 0]))
        for t, chunk, off, length, cid in sub[order].tolist():
            yield by_id[cid], t, self._data(chunk, off, length)

    def _data(self, chunk: int, off: int, length: int) -> bytes:
        assert self._file is not None
        if chunk < 0:
            self._file.seek(off)
            return self._file.read(length)
        if self._cache[0] != chunk:
            pos, n, compression = self._chunks[chunk]
            self._file.seek(pos)
            self._cache = (chunk, _decompress(self._file.read(n), compression))
        return self._cache[1][off:off + length]

    def deserialize(self, rawdata: bytes, typ: str) -> Any:
        """A message from its ROS 1 serialization."""
        return self.typestore.deserialize_ros1(rawdata, typ)

    def close(self) -> None:
        if self._file is not None:
            self._file.close()
            self._file = None
        self._cache = (-2, b"")

    def __enter__(self) -> UnindexedBag1Reader:
        self.open()
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.close()

"""`rosbag import` of unindexed ROS 1 bags: what `rosbag record` leaves when it is killed.

The bags are real: written by rosbags' writer (several chunks, none/bz2/lz4), then made
unindexed the way a killed recorder leaves them: the bag header's ``index_pos`` set to 0
and everything from the index (connection and chunk-info records after the last chunk)
cut off; for a recorder killed while writing, the file also ends inside the last chunk.
What should come out is worked out from rosbags' own index of the intact bag.
"""

from __future__ import annotations

import struct
from pathlib import Path

import pytest

pytest.importorskip("rosbags")
from rosbags.rosbag1 import Reader as Reader1  # noqa: E402
from test_rosbag import _scenario, write_test_bag  # noqa: E402

from sonarloc.io import rosbag  # noqa: E402
from sonarloc.io.logfile import OdomRecord, iter_log  # noqa: E402
from sonarloc.io.rosbag1_scan import UnindexedBag1Reader  # noqa: E402

CHUNK_BYTES = 1500  # ~9 chunks for the scenario's 53 messages


def _indexed(tmp_path: Path, compression: str | None) -> Path:
    ranges, odom = _scenario()
    bag = tmp_path / f"indexed_{compression or 'none'}.bag"
    write_test_bag(bag, 1, ranges=ranges, odom=odom, compression=compression,
                   chunk_bytes=CHUNK_BYTES)
    return bag


def _unindex(raw: bytes) -> bytes:
    """The bag with index_pos 0 and the index (everything from index_pos) removed."""
    at = raw.index(b"index_pos=", 0, 4096) + len(b"index_pos=")
    (index_pos,) = struct.unpack_from("<Q", raw, at)
    assert 4096 < index_pos < len(raw)
    return raw[:at] + bytes(8) + raw[at + 8:index_pos]


def _rosbags_index(bag: Path) -> tuple[list[tuple[str, int, bytes, tuple[int, int]]],
                                       dict[int, tuple[int, int]]]:
    """rosbags' messages of the intact bag, in its order: (topic, time ns, raw,
    (chunk pos, offset in the chunk)); and chunk pos -> (data pos, data size)."""
    out = []
    with Reader1(bag) as rd:
        seen = {c.id: 0 for c in rd.connections}
        for conn, t, raw in rd.messages():
            entry = rd.indexes[conn.id][seen[conn.id]]
            seen[conn.id] += 1
            assert entry.time == t
            out.append((conn.topic, t, raw, (entry.chunk_pos, entry.offset)))
        chunks = {pos: (c.datapos, c.datasize) for pos, c in rd.chunks.items()}
    return out, chunks


def _read_all(bag: Path) -> tuple[list[tuple[str, int, bytes]], UnindexedBag1Reader]:
    with UnindexedBag1Reader(bag, rosbag.typestore(1)) as reader:
        got = [(c.topic, t, raw) for c, t, raw in reader.messages()]
    return got, reader


@pytest.mark.parametrize("compression,name", [(None, "rec.bag"), ("bz2", "rec.bag.active"),
                                              ("lz4", "rec.bag")])
def test_unindexed_bag_imports_the_same_log(tmp_path: Path, compression: str | None,
                                            name: str) -> None:
    bag = _indexed(tmp_path, compression)
    expected, chunks = _rosbags_index(bag)
    assert len(chunks) >= 5 and len(expected) == 53
    cut = tmp_path / name
    cut.write_bytes(_unindex(bag.read_bytes()))
    if name.endswith(".bag"):
        with pytest.raises(Exception, match="Bag is not indexed"):  # rosbags alone
            with Reader1(cut):
                pass
    got, reader = _read_all(cut)
    assert got == [e[:3] for e in expected]
    assert (reader.report.chunks, reader.report.messages, reader.report.tail_bytes) == \
        (len(chunks), 53, 0)
    log_a, log_b = tmp_path / "indexed.jsonl", tmp_path / "unindexed.jsonl"
    stats_a = rosbag.import_bag(bag, log_a)
    stats_b = rosbag.import_bag(cut, log_b)
    assert log_b.read_bytes() == log_a.read_bytes()
    assert stats_a.unindexed is None and stats_b.unindexed is not None
    assert stats_b.summary() == stats_a.summary() + "; " + stats_b.unindexed.summary()
    assert "no truncated record" in stats_b.summary()


@pytest.mark.parametrize("compression", [None, "bz2"])
def test_killed_recorder_keeps_every_complete_message(tmp_path: Path, run_cli,
                                                      compression: str | None) -> None:
    bag = _indexed(tmp_path, compression)
    expected, chunks = _rosbags_index(bag)
    raw = bag.read_bytes()
    unindexed = _unindex(raw)
    # the recorder died half way through a chunk of several messages (the file's last
    # chunk can hold one): what came after it was never written
    last = max(p for p in chunks if sum(e[3][0] == p for e in expected) >= 3)
    data_pos, data_size = chunks[last]
    end = data_pos + data_size // 2
    cut = tmp_path / "rec.bag.active"
    cut.write_bytes(unindexed[:end])

    if compression is None:
        # an uncompressed chunk's records lie in the file as they are: every record that
        # ends before the cut is complete and kept; the cut one is the lost tail
        def record_end(offset: int) -> int:
            (hlen,) = struct.unpack_from("<I", raw, data_pos + offset)
            (dlen,) = struct.unpack_from("<I", raw, data_pos + offset + 4 + hlen)
            return data_pos + offset + 8 + hlen + dlen

        keep = [e for e in expected if e[3][0] < last or
                (e[3][0] == last and record_end(e[3][1]) <= end)]
        ends = sorted(record_end(e[3][1]) for e in keep if e[3][0] == last)
        tail_from = ends[-1] if ends else data_pos
        assert 0 < len(ends) < sum(e[3][0] == last for e in expected)
    else:
        keep = [e for e in expected if e[3][0] < last]
        tail_from = last  # the whole cut chunk record is lost
    assert len(keep) >= 20
    got, reader = _read_all(cut)
    assert got == [e[:3] for e in keep]
    assert reader.report.tail_bytes == end - tail_from > 0
    assert reader.report.chunks == sum(p < last for p in chunks)
    print(f"{compression}: kept {len(keep)} of {len(expected)} messages, "
          f"lost {end - tail_from} bytes")

    log = tmp_path / "rec.jsonl"
    proc = run_cli("rosbag", "import", str(cut), "--out", str(log))
    assert proc.returncode == 0, proc.stderr
    odom = [r for r in iter_log(log, strict=True) if isinstance(r, OdomRecord)]
    assert len(odom) == sum(e[0] == "/odom" for e in keep)
    assert "unindexed ROS 1 bag (index_pos 0) read sequentially" in proc.stderr
    assert f"the last {end - tail_from} bytes (from byte {tail_from}" in proc.stderr
    assert "truncated record and are lost" in proc.stderr


def test_recorder_killed_with_a_chunk_open(tmp_path: Path) -> None:
    # rosbag record writes a chunk's header with the sizes 0 and fixes them when the
    # chunk is closed: a killed recorder leaves that placeholder before the (uncompressed)
    # records of the open chunk
    bag = _indexed(tmp_path, None)
    expected, chunks = _rosbags_index(bag)
    raw = bag.read_bytes()
    unindexed = _unindex(raw)
    last = max(chunks)
    data_pos, data_size = chunks[last]
    head = bytearray(unindexed[last:data_pos])
    at = head.index(b"size=") + len(b"size=")
    head[at:at + 4] = bytes(4)
    head[-4:] = bytes(4)  # data length 0
    cut = tmp_path / "open.bag.active"
    cut.write_bytes(unindexed[:last] + bytes(head) + unindexed[data_pos:data_pos + data_size])
    got, reader = _read_all(cut)
    assert got == [e[:3] for e in expected]
    in_last = sum(e[3][0] == last for e in expected)
    assert reader.report.inline_messages == in_last > 0
    assert reader.report.tail_bytes == 0


def test_damaged_index_is_read_sequentially(tmp_path: Path) -> None:
    # an indexed bag whose copy stopped inside the index: rosbags finds the index damaged
    bag = _indexed(tmp_path, "bz2")
    raw = bag.read_bytes()
    at = raw.index(b"index_pos=", 0, 4096) + len(b"index_pos=")
    (index_pos,) = struct.unpack_from("<Q", raw, at)
    cut = tmp_path / "copy.bag"
    cut.write_bytes(raw[:index_pos + 20])
    with pytest.raises(Exception, match="Bag index looks damaged"):
        with Reader1(cut):
            pass
    log_a, log_b = tmp_path / "a.jsonl", tmp_path / "b.jsonl"
    rosbag.import_bag(bag, log_a)
    stats = rosbag.import_bag(cut, log_b)
    assert log_b.read_bytes() == log_a.read_bytes()
    assert stats.unindexed is not None and stats.unindexed.tail_bytes == 20


@pytest.mark.parametrize("name", ["junk.bag", "junk.bag.active"])
def test_a_file_that_is_not_a_bag_is_one_clear_line(tmp_path: Path, run_cli, name: str) -> None:
    junk = tmp_path / name
    junk.write_bytes(b"timestamp,range\n0.1,1.5\n" * 50)
    proc = run_cli("rosbag", "import", str(junk), "--out", str(tmp_path / "x.jsonl"))
    assert proc.returncode == 2
    assert proc.stderr.count("\n") == 1, proc.stderr
    assert proc.stderr.startswith(f"sonarloc rosbag: error: bag {junk}: ")
    if name.endswith(".active"):
        assert proc.stderr.endswith("not a ROS 1 bag (no '#ROSBAG V2.0' line)\n")
    else:
        assert "File magic is invalid" in proc.stderr   # rosbags' message, as before
    assert not (tmp_path / "x.jsonl").exists()


def test_bag_header_only(tmp_path: Path) -> None:
    # killed before the first chunk: a bag with no messages, not an error of the reader
    bag = _indexed(tmp_path, None)
    raw = _unindex(bag.read_bytes())
    cut = tmp_path / "early.bag.active"
    cut.write_bytes(raw[:4096 + 13 + 30])
    got, reader = _read_all(cut)
    assert got == [] and reader.report.tail_bytes == 30 and reader.report.chunks == 0
    with pytest.raises(rosbag.RosbagError, match="no sensor_msgs/msg/Range topics"):
        rosbag.import_bag(cut, tmp_path / "x.jsonl")


@pytest.mark.parametrize("compression", [None, "bz2"])
def test_any_cut_keeps_a_prefix_of_the_messages(tmp_path: Path, compression: str | None
                                                ) -> None:
    # wherever the file ends, the reader keeps whole messages of the intact bag (in its
    # order, fewer for an earlier cut) and accounts for every byte: read + lost = size
    bag = _indexed(tmp_path, compression)
    expected, _ = _rosbags_index(bag)
    full = [e[:3] for e in expected]
    unindexed = _unindex(bag.read_bytes())
    cut = tmp_path / "cut.bag.active"
    previous = -1
    step = len(unindexed) // 100 | 1   # ~100 cuts, at odd offsets
    for end in [*range(13, len(unindexed), step), len(unindexed)]:
        cut.write_bytes(unindexed[:end])
        if end < 4096 + 13:   # the bag header record (4096 bytes) is not complete
            if b"chunk_count=" not in unindexed[:end]:   # its fields are not complete
                with pytest.raises(rosbag.RosbagError, match="no complete bag header record"):
                    with rosbag._open_reader(cut):
                        pass
            else:   # its padding is cut: an empty bag, all of it lost
                got, reader = _read_all(cut)
                assert got == [] and reader.report.tail_pos == 13
            continue
        got, reader = _read_all(cut)
        kept = set(got)
        assert [m for m in full if m in kept] == got
        assert len(got) >= previous
        previous = len(got)
        rep = reader.report
        assert rep.size_bytes == end and 0 <= rep.tail_bytes < end - 4096
        assert (rep.tail_bytes == 0) == (rep.tail_pos is None)
    assert got == full and rep.tail_bytes == 0   # the whole unindexed file

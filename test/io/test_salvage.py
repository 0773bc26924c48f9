"""ficap_ros.io.salvage: every whole message before the damage of a cut or damaged MCAP (or sqlite3)
bag, and an honest account of what was lost."""

from __future__ import annotations

import io
import shutil
import tempfile
import zlib
from pathlib import Path

import lz4.frame
import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from mcap.data_stream import RecordBuilder
from mcap.records import Channel, Chunk, Message, Schema
from mcap.stream_reader import StreamReader
from mcap.writer import CompressionType, Writer

from ficap_ros.errors import BagError
from ficap_ros.geometry.camera import CameraModel
from ficap_ros.io import messages
from ficap_ros.io.bag_writer import BagWriter
from ficap_ros.io.messages import ROSBAGS, jazzy_typestore
from ficap_ros.io.salvage import NothingSalvaged, SalvageReader
from ficap_ros.io.sources import CAMERA_INFO_TYPE, IMAGE_TYPE

N = 12
T0 = 1_000


def _rosbags_mcap(folder: Path) -> Path:
    """A rosbag2 folder (one uncompressed chunk) of N CameraInfo + Image pairs."""
    cam = CameraModel.pinhole(64, 48, f_px=50.0)
    with BagWriter(folder) as w:
        w.add_topic("/cam/image_raw", IMAGE_TYPE)
        w.add_topic("/cam/camera_info", CAMERA_INFO_TYPE)
        for i in range(N):
            img = np.random.default_rng(i).integers(0, 256, (48, 64), dtype=np.uint8)
            head = messages.header(ROSBAGS, T0 + i, "cam")
            w.write("/cam/camera_info", T0 + i, messages.camera_info(ROSBAGS, head, cam))
            w.write("/cam/image_raw", T0 + i, messages.image(ROSBAGS, head, img, "mono8"))
    return next(folder.glob("*.mcap"))


def _rewritten(data: bytes, **writer_options: object) -> bytes:
    """The same records through mcap's own writer (chunking and compression as given)."""
    out = io.BytesIO()
    writer = Writer(out, **writer_options)
    writer.start("ros2", "ficap test")
    for r in StreamReader(io.BytesIO(data)).records:
        if isinstance(r, Schema):
            writer.register_schema(r.name, r.encoding, r.data)
        elif isinstance(r, Channel):
            writer.register_channel(r.topic, r.message_encoding, r.schema_id, r.metadata)
        elif isinstance(r, Message):
            writer.add_message(r.channel_id, r.log_time, r.data, r.publish_time, r.sequence)
    writer.finish()
    return out.getvalue()


def _zstd(lz4_data: bytes) -> bytes:
    """An lz4-chunked file with every chunk recompressed with zstd (mcap's writer needs the
    zstandard package for that; the salvage decodes zstd with the standard library's)."""
    try:
        from compression import zstd  # Python 3.14
    except ImportError:
        from backports import zstd  # type: ignore[no-redef]
    out = RecordBuilder()
    out.write(b"\x89MCAP0\r\n")
    for r in StreamReader(io.BytesIO(lz4_data), emit_chunks=True).records:
        if isinstance(r, Chunk):
            raw = lz4.frame.decompress(r.data)
            r = Chunk(compression="zstd", data=zstd.compress(raw),
                      message_start_time=r.message_start_time, message_end_time=r.message_end_time,
                      uncompressed_crc=zlib.crc32(raw), uncompressed_size=len(raw))
        r.write(out)
    out.write(b"\x89MCAP0\r\n")
    return out.end()


@pytest.fixture(scope="module")
def scratch() -> Path:
    with tempfile.TemporaryDirectory(prefix="ficap-salvage-") as path:
        yield Path(path)


class _Layouts(dict):
    """Layout name -> file bytes (shown by name in a failing example, not byte by byte)."""

    def __repr__(self) -> str:
        return f"<MCAP layouts {', '.join(self)}>"


@pytest.fixture(scope="module")
def files(scratch: Path) -> dict[str, bytes]:
    """The same recording in every MCAP layout the salvage meets."""
    plain = _rosbags_mcap(scratch / "bag").read_bytes()
    lz4_small = _rewritten(plain, compression=CompressionType.LZ4, chunk_size=3000)
    return _Layouts({
        "rosbags": plain,
        "lz4": lz4_small,
        "zstd": _zstd(lz4_small),
        "small_chunks": _rewritten(plain, compression=CompressionType.NONE, chunk_size=2500),
        "unchunked": _rewritten(plain, use_chunking=False),
    })


def _full(data: bytes) -> list[tuple[str, int, bytes]]:
    """(topic, log time, payload) of every message, by mcap's reader of the intact file."""
    topics: dict[int, str] = {}
    out = []
    for r in StreamReader(io.BytesIO(data)).records:
        if isinstance(r, Channel):
            topics[r.id] = r.topic
        elif isinstance(r, Message):
            out.append((topics[r.channel_id], r.log_time, r.data))
    return out


def _chunk_ends(data: bytes) -> list[tuple[int, int, int]]:
    """(start of its compressed records, record end, message end time ns) of every chunk of an
    intact file (the records follow the record header and the chunk's own header)."""
    out = []
    pos = 8
    for r in StreamReader(io.BytesIO(data), emit_chunks=True).records:
        length = int.from_bytes(data[pos + 1: pos + 9], "little")
        if isinstance(r, Chunk):
            records = pos + 9 + 8 + 8 + 8 + 4 + 4 + len(r.compression.encode()) + 8
            out.append((records, pos + 9 + length, r.message_end_time))
        pos += 9 + length
    return out


def _salvage(path: Path) -> tuple[list[tuple[str, int, bytes]], object]:
    reader = SalvageReader(path, jazzy_typestore())
    try:
        got = [(c.topic, t, bytes(raw)) for c, t, raw in reader.messages()]
        return got, reader.damage
    finally:
        reader.close()


@given(fraction=st.floats(0.02, 1.0))
def test_an_uncompressed_mcap_cut_anywhere_gives_every_whole_message_before_the_cut(
        files: dict[str, bytes], scratch: Path, fraction: float) -> None:
    """Exactly the messages whose records end before the cut, in order, and where the file
    ends; a cut inside a chunk says until when its messages ran."""
    for layout in ("rosbags", "small_chunks", "unchunked"):
        data = files[layout]
        cut = int(len(data) * fraction)
        path = scratch / "cut.mcap"
        path.write_bytes(data[:cut])
        full = _full(data)
        # Uncompressed: a message's payload lies in the file, its record ends with it.
        whole = [m for m in full if data.find(m[2]) + len(m[2]) <= cut]
        try:
            got, damage = _salvage(path)
        except NothingSalvaged as err:
            assert not whole and "cut.mcap" in err.detail
            continue
        assert got == whole, layout
        footer = len(data) - 8 - (9 + 20)  # the footer record, then the closing magic
        if cut >= footer + 9:  # the footer's opcode and length are there: nothing is lost
            assert damage is None
            continue
        assert damage is not None and "cut.mcap" in damage.detail
        assert damage.last_good_ns == max(t for _, t, _ in whole)
        # Cut inside a chunk's records: its header says until when they ran.
        inside = [end_ns for records, end, end_ns in _chunk_ends(data) if records <= cut < end]
        assert damage.lost_until_ns == (inside[0] if inside else None), (layout, cut)


@pytest.mark.parametrize("layout", ["lz4", "zstd"])
def test_a_compressed_chunk_cut_short_gives_up_the_messages_its_prefix_holds(
        files: dict[str, bytes], scratch: Path, layout: str) -> None:
    """Every cut of a compressed file: a prefix of the messages, growing with the cut, each
    complete; all of them when nothing is cut."""
    data = files[layout]
    full = _full(data)
    path = scratch / f"{layout}.mcap"
    counts = []
    for cut in range(200, len(data) + 1, max(1, len(data) // 300)):
        path.write_bytes(data[:cut])
        try:
            got, damage = _salvage(path)
        except NothingSalvaged:
            got, damage = [], "nothing"
        assert got == full[:len(got)]
        assert damage is not None
        counts.append(len(got))
    assert counts == sorted(counts) and 0 < counts[len(counts) // 2] < len(full)
    path.write_bytes(data)
    got, damage = _salvage(path)
    assert got == full and damage is None
    # A cut inside the last chunk's records keeps some of them (decoded as far as the bytes go).
    start, end, end_ns = _chunk_ends(data)[-1]  # start: of the chunk's compressed records
    path.write_bytes(data[: (start + end) // 2 + 40])
    got, damage = _salvage(path)
    before = sum(1 for _, t, _ in full if t < T0 + N - 2)
    assert len(got) >= before - 4 and damage.lost_until_ns == end_ns
    assert "ends inside a chunk" in damage.detail


def test_metadata_yaml_gives_the_lost_range_and_expected_counts(files: dict[str, bytes],
                                                                scratch: Path) -> None:
    folder = scratch / "with_metadata"
    shutil.rmtree(folder, ignore_errors=True)
    mcap = _rosbags_mcap(folder)
    data = mcap.read_bytes()
    mcap.write_bytes(data[: int(len(data) * 0.6)])
    got, damage = _salvage(folder)
    assert 0 < len(got) < 2 * N
    assert damage.expected_counts == {"/cam/image_raw": N, "/cam/camera_info": N}
    assert damage.lost_until_ns == T0 + N - 1  # the bag's end, from metadata.yaml
    reader = SalvageReader(folder, jazzy_typestore())
    try:
        counts = {c.topic: c.msgcount for c in reader.connections}
        assert sum(counts.values()) == len(got)
        assert {c.msgtype for c in reader.connections} == {IMAGE_TYPE, CAMERA_INFO_TYPE}
    finally:
        reader.close()


def test_a_malformed_record_is_reported_and_the_rest_still_read(files: dict[str, bytes],
                                                                 scratch: Path) -> None:
    """A Message record whose length is too short for its own fields: mcap's reader cannot take
    it, the salvage says so and keeps every other message."""
    data = bytearray(files["unchunked"])
    full = _full(bytes(data))
    third = data.find(full[2][2]) - 22 - 9  # the third message's record
    assert data[third] == 0x05
    data[third + 1: third + 9] = (10).to_bytes(8, "little")  # 10 bytes: not even its header
    path = scratch / "malformed.mcap"
    path.write_bytes(bytes(data))
    got, damage = _salvage(path)
    assert got[:2] == full[:2] and damage is not None and "malformed" in damage.detail


def test_files_with_nothing_to_salvage(files: dict[str, bytes], scratch: Path) -> None:
    path = scratch / "bad.mcap"
    path.write_bytes(b"not an mcap file at all, just text" * 3)
    with pytest.raises(BagError, match="not an MCAP file"):
        _salvage(path)
    for data, detail in ((b"\x89MCA", "cut before its first record"),
                         (files["rosbags"][:8], "no footer"),
                         (files["rosbags"][:40], "ends inside a record")):
        path.write_bytes(data)
        with pytest.raises(NothingSalvaged) as err:
            _salvage(path)
        assert detail in err.value.detail and "bad.mcap" in err.value.detail


def test_a_torn_sqlite3_bag_gives_its_first_messages(scratch: Path) -> None:
    folder = scratch / "sq"
    shutil.rmtree(folder, ignore_errors=True)
    with BagWriter(folder, storage="sqlite3") as w:
        w.add_topic("/cam/image_raw", IMAGE_TYPE)
        for i in range(40):
            img = np.full((48, 64), i, np.uint8)
            w.write("/cam/image_raw", T0 + i,
                    messages.image(ROSBAGS, messages.header(ROSBAGS, T0 + i, "cam"), img, "mono8"))
    db = next(folder.glob("*.db3"))
    torn = db.read_bytes()[: db.stat().st_size * 7 // 10]
    db.write_bytes(torn)
    got, damage = _salvage(folder)
    assert 0 < len(got) < 40 and [t for _, t, _ in got] == list(range(T0, T0 + len(got)))
    assert damage is not None and damage.expected_counts == {"/cam/image_raw": 40}
    assert db.read_bytes() == torn  # the input is only read


def test_a_cut_sqlite3_bag_is_read_in_place(scratch: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Nothing is copied: the salvage reads the file through its VFS (no temporary file is made),
    a page past the cut is a corrupt page to SQLite (never zeros in a message), and the rows read
    are the whole-page ones, byte for byte."""
    folder = scratch / "sq_in_place"
    shutil.rmtree(folder, ignore_errors=True)
    images = [np.full((48, 64), i, np.uint8) for i in range(30)]
    with BagWriter(folder, storage="sqlite3") as w:
        w.add_topic("/cam/image_raw", IMAGE_TYPE)
        for i, img in enumerate(images):
            w.write("/cam/image_raw", T0 + i,
                    messages.image(ROSBAGS, messages.header(ROSBAGS, T0 + i, "cam"), img, "mono8"))
    db = next(folder.glob("*.db3"))
    db.write_bytes(db.read_bytes()[: db.stat().st_size * 6 // 10 + 123])  # not on a page edge
    def no_copy(*args: object, **kwargs: object) -> None:
        raise AssertionError("the salvage made a temporary file")

    for name in ("mkdtemp", "mkstemp", "NamedTemporaryFile", "TemporaryFile"):
        monkeypatch.setattr(tempfile, name, no_copy)
    with SalvageReader(folder, jazzy_typestore()) as reader:
        got = [(t, reader.deserialize(raw, c.msgtype)) for c, t, raw in reader.messages()]
        assert "cut short" in reader.damage.detail
    monkeypatch.undo()
    assert 0 < len(got) < 30
    for (t, msg), img in zip(got, images):
        assert bytes(msg.data) == img.tobytes()


def test_a_chunk_index_that_does_not_fit_its_file_is_not_trusted(files: dict[str, bytes],
                                                                  scratch: Path) -> None:
    """An indexed file whose summary names a chunk of a corrupt size: read front to back by the
    salvage (rosbags would read the rest of the file for it)."""
    from mcap.reader import make_reader

    from ficap_ros.io.salvage import index_damage

    path = scratch / "indexed.mcap"
    path.write_bytes(files["rosbags"])
    assert index_damage(path) == ""
    summary = make_reader(io.BytesIO(files["rosbags"])).get_summary()
    start = summary.chunk_indexes[0].chunk_start_offset
    data = bytearray(files["rosbags"])
    data[start + 1: start + 9] = (1 << 40).to_bytes(8, "little")  # the chunk record's length
    path.write_bytes(bytes(data))
    assert "is not the chunk its index names" in index_damage(path)
    got, damage = _salvage(path)
    assert damage is not None and "claims 1099511627776 bytes" in damage.detail

"""What survives of a damaged recording: every complete message before the damage.

A killed recorder or a full disk leaves an MCAP file without its footer and summary (rosbags'
indexed reader then refuses the whole file: "File end magic is invalid"), or a sqlite3 database
cut short ("database disk image is malformed"). ``SalvageReader`` reads such files front to back
and offers the part of rosbags' ``AnyReader`` interface the bag tools use (``connections``,
``messages``, ``deserialize``, ``close``), plus what it could not read (``damage``).

* MCAP: records are walked in file order. Each is located by its opcode and length and checked
  against the bytes that follow; whole records are read by mcap's own ``StreamReader`` (one
  record at a time, so a malformed one cannot make it read into the next). A chunk cut short is
  decompressed as far as its bytes go (no compression, zstd and lz4 all decode a prefix) and its
  whole records are kept; the chunk header still says until when its messages ran, which bounds
  the lost time range.
* sqlite3: the database is read in place through a read-only SQLite VFS that shows it cut to
  whole pages with the header's page count set to match (no copy, nothing read ahead), and the
  messages table is read in rowid order (the order the recorder inserted them) until the first
  unreadable page.

Message definitions come from the file (MCAP schemas, rosbag2's ``message_definitions`` table)
when the Jazzy typestore does not know a type.
"""

from __future__ import annotations

import os
import struct
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterator, Sequence

from mcap.data_stream import ReadDataStream
from mcap.exceptions import McapError
from mcap.opcode import Opcode
from mcap.records import Channel, Chunk, McapRecord, Message, Schema
from mcap.stream_reader import MAGIC_SIZE, StreamReader, read_magic

from ficap_ros.errors import BagError
from ficap_ros.files import load_yaml

__all__ = ["SalvageConnection", "Damage", "SalvageReader", "NothingSalvaged", "storage_files",
           "index_damage", "MAX_RECORD_BYTES"]


class NothingSalvaged(BagError):
    """A bag file that is damaged (cut short, a malformed record) and holds no complete message
    before the damage; ``detail`` says where its bytes end (for the caller's one-line error)."""

    def __init__(self, message: str, detail: str) -> None:
        super().__init__(message)
        self.detail = detail


@dataclass(frozen=True)
class SalvageConnection:
    """A topic of a salvaged file (the fields of rosbags' ``Connection`` the tools read)."""

    id: int
    topic: str
    msgtype: str
    msgcount: int


@dataclass(frozen=True)
class Damage:
    """What could not be read.

    Attributes:
        detail: one line: where and how the file is damaged.
        last_good_ns: log time of the last message recovered (0 when none).
        lost_until_ns: log time until which messages were lost, when the file says (the header
            of a chunk cut short, or the bag's metadata.yaml), else None.
        expected_counts: messages per topic the bag's metadata.yaml promises, when it has one.
    """

    detail: str
    last_good_ns: int
    lost_until_ns: int | None
    expected_counts: dict[str, int] | None


def storage_files(path: Path) -> list[Path]:
    """The MCAP/sqlite3 files of a bag: the file itself, or a folder's, in name order."""
    if path.is_dir():
        return sorted(p for p in path.iterdir() if p.suffix.lower() in (".mcap", ".db3"))
    return [path]


def _metadata(path: Path) -> tuple[dict[str, int] | None, int | None]:
    """(message count per topic, end time ns) from a rosbag2 folder's metadata.yaml, if any."""
    meta = (path if path.is_dir() else path.parent) / "metadata.yaml"
    if not meta.is_file():
        return None, None
    try:
        info = load_yaml(meta, "metadata", BagError)["rosbag2_bagfile_information"]
        counts = {str(t["topic_metadata"]["name"]): int(t["message_count"])
                  for t in info["topics_with_message_count"]}
        end = int(info["starting_time"]["nanoseconds_since_epoch"]) + int(
            info["duration"]["nanoseconds"])
        files = [str(f) for f in info.get("relative_file_paths", [])]
    except Exception:  # noqa: BLE001 - a damaged metadata.yaml only means no expected counts
        return None, None
    if path.is_file() and files and path.name not in files:
        return None, None  # a metadata.yaml beside the file, but of another bag
    return counts, end


# -- MCAP ----------------------------------------------------------------------------------------
#: A record's opcode (1 byte) and body length (8 bytes, little-endian) before its body.
_RECORD_HEADER = struct.Struct("<BQ")
#: Records the salvage needs (the rest are indexes and summaries of what it walks anyway).
_DATA_OPCODES = frozenset({Opcode.SCHEMA, Opcode.CHANNEL, Opcode.MESSAGE})
#: Largest record the salvage reads, and the most a chunk may decompress to: a chunk holds the
#: largest images a recorder writes (a 4K raw frame is 25 MB, the pixel budget's largest
#: colour image 120 MB). A longer one has a corrupt length: reading it would copy the file.
MAX_RECORD_BYTES = 128 << 20
#: Bytes fed to a decompressor at a time (a cut chunk's prefix is decompressed as a stream).
_PIECE_BYTES = 1 << 20


class _Exact:
    """Bytes for mcap's ``ReadDataStream`` that give every read all it asks or nothing.

    mcap's stream returns a short read as it is and fails only on an empty one, so over a whole
    file a field that overruns its record would read the next record's bytes. Over one record's
    bytes an overrun is ``EndOfFile`` instead: the record is malformed.
    """

    def __init__(self, data: bytes) -> None:
        self._data = memoryview(data)
        self._pos = 0

    def read(self, n: int = -1) -> bytes:
        if n < 0 or self._pos + n > len(self._data):
            return b""
        out = bytes(self._data[self._pos: self._pos + n])
        self._pos += n
        return out


class _Malformed(Exception):
    """A whole record whose fields do not fit its length (or are not UTF-8 where text)."""


@dataclass(frozen=True)
class _Frame:
    """One record located by its header: ``offset`` in its buffer, ``opcode`` (-1 when the
    9-byte header itself is cut), body ``length`` as declared, ``complete`` when every byte of
    the body is there."""

    offset: int
    opcode: int
    length: int
    complete: bool

    @property
    def end(self) -> int:
        return self.offset + _RECORD_HEADER.size + self.length


def _frames(data: Any, start: int) -> Iterator[_Frame]:
    """The records of ``data`` (a chunk's bytes) from ``start``, each length-checked against the
    bytes there: a cut record is the last one.

    mcap's ``StreamReader`` assumes whole records (it reads a cut one's remaining fields as
    whatever bytes are left, then fails), so the salvage locates each record first and hands
    mcap only whole ones.
    """
    pos = start
    while pos + _RECORD_HEADER.size <= len(data):
        opcode, length = _RECORD_HEADER.unpack_from(data, pos)
        frame = _Frame(pos, opcode, length, pos + _RECORD_HEADER.size + length <= len(data))
        yield frame
        if not frame.complete:
            return
        pos = frame.end
    if pos < len(data):
        yield _Frame(pos, -1, 0, False)  # a record header cut short


def _file_frames(fd: int, size: int, start: int) -> Iterator[_Frame]:
    """``_frames`` over a file of ``size`` bytes: each record's header read on its own
    (``os.pread``), so walking a file never holds more than one record of it."""
    pos = start
    while pos + _RECORD_HEADER.size <= size:
        opcode, length = _RECORD_HEADER.unpack(os.pread(fd, _RECORD_HEADER.size, pos))
        frame = _Frame(pos, opcode, length, pos + _RECORD_HEADER.size + length <= size)
        yield frame
        if not frame.complete:
            return
        pos = frame.end
    if pos < size:
        yield _Frame(pos, -1, 0, False)  # a record header cut short


def _read_record(record: bytes | memoryview) -> McapRecord:
    """One whole record (header and body) by mcap's stream reader.

    Raises:
        _Malformed: its fields overrun its length, or a text field is not UTF-8.
    """
    reader = StreamReader(_Exact(record), skip_magic=True, emit_chunks=True,
                          record_size_limit=None)
    try:
        return next(iter(reader.records))
    except (McapError, UnicodeDecodeError, ValueError, struct.error) as err:
        raise _Malformed(str(err)) from None


@dataclass(frozen=True)
class _ChunkHead:
    """The fields before a chunk's compressed records: the end of its messages' log times (ns),
    its compression, the declared length of the records and where they start in the body."""

    message_end_ns: int
    compression: str
    records_length: int
    records_offset: int


def _chunk_head(body: bytes) -> _ChunkHead | None:
    """The header of a chunk mcap's ``Chunk.read`` cannot take whole (the record is cut short,
    or its records' length disagrees with the record's); None when the header itself is cut.

    The fields are mcap's ``Chunk`` ones in its order, read with mcap's ``ReadDataStream``; the
    compression name is decoded leniently (an unknown one only makes the records unreadable).
    """
    stream = ReadDataStream(_Exact(body))
    try:
        stream.read8()  # message start time
        end_ns = stream.read8()
        stream.read8()  # uncompressed size
        stream.read4()  # uncompressed CRC
        compression = stream.read(stream.read4()).decode("utf-8", "replace")
        length = stream.read8()
    except McapError:
        return None
    return _ChunkHead(end_ns, compression, length, stream.count)


def _decompressor(compression: str) -> Any:
    if compression == "zstd":
        try:
            from compression import zstd  # Python 3.14
        except ImportError:
            from backports import zstd  # type: ignore[no-redef]
        return zstd.ZstdDecompressor()
    if compression == "lz4":
        import lz4.frame

        return lz4.frame.LZ4FrameDecompressor()
    return None


def _decompress_prefix(compression: str, data: bytes | memoryview) -> bytes | memoryview:
    """As much of a chunk's records as a (possibly cut) compressed buffer holds, at most
    ``MAX_RECORD_BYTES``: fed piece by piece, so neither a buffer that runs on past the chunk's
    end (a corrupt length) nor one that expands without end is held whole."""
    if compression == "":
        return data
    decompressor = _decompressor(compression)
    if decompressor is None:
        return b""
    view, out, budget = memoryview(data), [], MAX_RECORD_BYTES
    try:
        for start in range(0, len(view), _PIECE_BYTES):
            piece = decompressor.decompress(view[start: start + _PIECE_BYTES], max_length=budget)
            out.append(piece)
            budget -= len(piece)
            if decompressor.eof or budget <= 0:
                break
    except Exception:  # noqa: BLE001 - the damaged rest of a compressed stream holds nothing
        pass
    return b"".join(out)


def index_damage(path: Path) -> str:
    """Why an indexed MCAP file's chunk index cannot be trusted ('' when it can, or when the file
    has no index: its reader then finds the damage itself).

    rosbags reads an indexed file's chunks where its summary says, as long as it says: a corrupt
    offset or size there would make it read (and copy) the rest of the file. Each chunk index is
    checked against the file (inside it, sizes at most ``MAX_RECORD_BYTES``) and against the
    chunk record's own header (one 9-byte read per chunk).
    """
    from mcap.reader import make_reader

    try:
        with open(path, "rb") as handle:
            size = os.fstat(handle.fileno()).st_size
            summary = make_reader(handle).get_summary()
            for index in (summary.chunk_indexes if summary is not None else ()):
                start, length = index.chunk_start_offset, index.chunk_length
                if not (0 < start and start + length <= size and length > _RECORD_HEADER.size
                        and index.compressed_size < length
                        and index.uncompressed_size <= MAX_RECORD_BYTES):
                    return (f"{path.name}: the chunk index of the chunk at byte {start} does not "
                            "fit the file")
                opcode, declared = _RECORD_HEADER.unpack(
                    os.pread(handle.fileno(), _RECORD_HEADER.size, start))
                if opcode != Opcode.CHUNK or declared != length - _RECORD_HEADER.size:
                    return (f"{path.name}: the record at byte {start} is not the chunk its index "
                            "names (a corrupt length or offset)")
    except Exception:  # noqa: BLE001 - no readable summary: the reader decides
        return ""
    return ""


class _McapFile:
    """One MCAP file walked front to back: records located and length-checked here, read by
    mcap's ``StreamReader``; a chunk cut short gives up the whole records its prefix holds."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.schemas: dict[int, tuple[str, str, bytes]] = {}
        self.channels: dict[int, tuple[str, int]] = {}
        self.damage = ""
        self.lost_until_ns: int | None = None

    def messages(self) -> Iterator[tuple[int, int, bytes]]:
        """(channel id, log time, payload) of every complete message, in file order."""
        with open(self.path, "rb") as handle:
            fd = handle.fileno()
            size = os.fstat(fd).st_size
            if size < MAGIC_SIZE:
                self.damage = f"{self.path.name} is empty or cut before its first record"
                return
            try:
                read_magic(ReadDataStream(_Exact(os.pread(fd, MAGIC_SIZE, 0))))
            except McapError:
                raise BagError(f"{self.path} is not an MCAP file") from None
            yield from self._walk(fd, size)

    def _walk(self, fd: int, size: int) -> Iterator[tuple[int, int, bytes]]:
        """The data section's records up to the footer, or up to the first record cut short or
        of a corrupt length (each record read on its own, at most ``MAX_RECORD_BYTES``)."""
        footer = False
        for frame in _file_frames(fd, size, MAGIC_SIZE):
            if frame.opcode == Opcode.FOOTER:
                footer = True
                break
            if frame.opcode == 0:  # reserved: zeros (a file extended or overwritten with them)
                self.damage = self.damage or (f"{self.path.name} holds no record at byte "
                                              f"{frame.offset} of {size} (zeros)")
                break
            huge = frame.length > MAX_RECORD_BYTES
            if huge:
                self.damage = self.damage or (
                    f"a record of {self.path.name} at byte {frame.offset} claims {frame.length} "
                    f"bytes, more than any recording writes (a corrupt length)")
            if frame.opcode == Opcode.CHUNK:
                whole = frame.complete and not huge
                record = os.pread(fd, min(frame.end, size, frame.offset + _RECORD_HEADER.size
                                          + MAX_RECORD_BYTES) - frame.offset, frame.offset)
                yield from self._chunk(record, whole, frame.offset, size)
            elif frame.complete and not huge and frame.opcode in _DATA_OPCODES:
                yield from self._record(os.pread(fd, frame.end - frame.offset, frame.offset))
            if huge:
                break
            if not frame.complete:
                self.damage = self.damage or (
                    f"{self.path.name} ends inside a record at byte {frame.offset} of "
                    f"{size} (no footer)")
                break
        if not footer and not self.damage:
            self.damage = f"{self.path.name} has no footer (file cut short)"

    def _record(self, record: bytes) -> Iterator[tuple[int, int, bytes]]:
        """A schema or channel is kept, a message yielded as (channel id, log time, payload)."""
        try:
            parsed = _read_record(record)
        except _Malformed:
            self.damage = self.damage or f"a record of {self.path.name} is malformed"
            return
        if isinstance(parsed, Schema):
            self.schemas[parsed.id] = (parsed.name, parsed.encoding, parsed.data)
        elif isinstance(parsed, Channel):
            self.channels[parsed.id] = (parsed.topic, parsed.schema_id)
        elif isinstance(parsed, Message):
            yield parsed.channel_id, parsed.log_time, parsed.data

    def _chunk(self, record: bytes, complete: bool, offset: int,
               size: int) -> Iterator[tuple[int, int, bytes]]:
        """A chunk's messages: all of a whole one, the whole records of a cut one's prefix (the
        cut chunk's header still says until when its messages ran)."""
        if complete:
            try:
                chunk = _read_record(record)
            except _Malformed:
                chunk = None
            if isinstance(chunk, Chunk):
                yield from self._inner(_decompress_prefix(chunk.compression, chunk.data), True)
                return
        body = memoryview(record)[_RECORD_HEADER.size:]
        head = _chunk_head(body)
        if head is None:
            self.damage = (f"{self.path.name} ends inside a chunk header at byte {offset} of "
                           f"{size}")
            return
        payload = body[head.records_offset: head.records_offset + head.records_length]
        whole = complete and len(payload) == head.records_length
        if not whole:
            self.lost_until_ns = head.message_end_ns
            self.damage = self.damage or (f"{self.path.name} ends inside a chunk at byte {offset} "
                                          f"of {size} (no footer)")
        yield from self._inner(_decompress_prefix(head.compression, payload), whole)

    def _inner(self, records: bytes | memoryview,
               complete: bool) -> Iterator[tuple[int, int, bytes]]:
        """The records of a chunk's decompressed bytes (of a cut chunk: up to the one cut)."""
        for frame in _frames(records, 0):
            if frame.opcode == 0:  # reserved: zeros where records should be
                self.damage = self.damage or "a chunk holds an invalid record (zeros)"
                return
            if not frame.complete:
                if complete:
                    self.damage = self.damage or "a record inside a chunk is cut short"
                return
            if frame.opcode in _DATA_OPCODES:
                yield from self._record(records[frame.offset: frame.end])


# -- sqlite3 -------------------------------------------------------------------------------------
#: Files the salvage's SQLite VFS serves: real path -> (bytes of its whole pages, their count).
_CUT_FILES: dict[str, tuple[int, int]] = {}
_VFS_NAME = "ficap-salvage"
_VFS: Any = None


def _salvage_vfs() -> str:
    """A read-only SQLite VFS (apsw's, registered once) that shows a database cut short as its
    whole pages, with the header's page count set to match: the input is read in place, never
    copied, and a page past the cut is a corrupt page to SQLite, not zeros in a message."""
    global _VFS
    if _VFS is not None:
        return _VFS_NAME
    import apsw

    class CutFile(apsw.VFSFile):
        def __init__(self, name: Any, flags: list[int]) -> None:
            path = name.filename() if isinstance(name, apsw.URIFilename) else str(name)
            super().__init__("", name, flags)
            self._size, self._pages = _CUT_FILES[path]

        def xRead(self, amount: int, offset: int) -> bytes:  # noqa: N802 - apsw's name
            if offset >= self._size:
                return b""
            data = super().xRead(min(amount, self._size - offset), offset)
            if offset <= 28 and offset + len(data) >= 32:
                head = bytearray(data)
                head[28 - offset: 32 - offset] = struct.pack(">I", self._pages)
                data = bytes(head)
            return data

        def xFileSize(self) -> int:  # noqa: N802 - apsw's name
            return self._size

    class CutVFS(apsw.VFS):
        def __init__(self) -> None:
            super().__init__(_VFS_NAME, "")

        def xOpen(self, name: Any, flags: list[int]) -> Any:  # noqa: N802 - apsw's name
            return CutFile(name, flags)

    _VFS = CutVFS()
    return _VFS_NAME


def _sqlite_header(path: Path) -> tuple[int, int, str]:
    """(bytes of the file's whole pages, their count, what is cut) from its header; only the
    100-byte header is read."""
    try:
        with open(path, "rb") as handle:
            size = os.fstat(handle.fileno()).st_size
            head = handle.read(100)
    except OSError as err:
        raise BagError(f"cannot read {path}: {err.strerror or err}") from err
    if len(head) < 100 or not head.startswith(b"SQLite format 3\x00"):
        raise BagError(f"{path} is not an SQLite database")
    (page,) = struct.unpack(">H", head[16:18])
    page = 65536 if page == 1 else page
    if page < 512 or page & (page - 1):
        raise BagError(f"{path} has an invalid SQLite header")
    (header_pages,) = struct.unpack(">I", head[28:32])
    pages = size // page
    detail = ""
    if size % page or (header_pages and pages < header_pages):
        detail = (f"{path.name} is cut short ({size} bytes, {pages} whole pages of "
                  f"{header_pages or '?'})")
    return pages * page, pages, detail


class _SqliteFile:
    """One rosbag2 sqlite3 file read in place (``_salvage_vfs``), in rowid order, up to the first
    unreadable page."""

    def __init__(self, path: Path) -> None:
        import apsw

        self.path = path
        size, pages, self.damage = _sqlite_header(path)
        self._key = os.path.abspath(path)
        _CUT_FILES[self._key] = (size, pages)
        self.lost_until_ns: int | None = None
        self.topics: dict[int, tuple[str, str]] = {}
        self.definitions: dict[str, tuple[str, str]] = {}
        con = self._connect()
        try:
            for tid, name, msgtype in con.execute("SELECT id, name, type FROM topics"):
                self.topics[int(tid)] = (str(name), str(msgtype))
            try:
                for msgtype, enc, text in con.execute(
                        "SELECT topic_type, encoding, encoded_message_definition "
                        "FROM message_definitions"):
                    self.definitions[str(msgtype)] = (str(enc), str(text))
            except apsw.Error:
                pass  # rosbag2 before Iron: no definitions table
        except apsw.Error as err:
            raise BagError(f"cannot read {path}: {err}") from err
        finally:
            con.close()

    def _connect(self) -> Any:
        import apsw

        try:
            return apsw.Connection(f"file:{self._key}?mode=ro&immutable=1",
                                   flags=apsw.SQLITE_OPEN_READONLY | apsw.SQLITE_OPEN_URI,
                                   vfs=_salvage_vfs())
        except apsw.Error as err:
            raise BagError(f"cannot read {self.path}: {err}") from err

    def messages(self) -> Iterator[tuple[int, int, bytes]]:
        import apsw

        con = self._connect()
        try:
            rows = iter(con.execute("SELECT topic_id, timestamp, data FROM messages ORDER BY id"))
            while True:
                try:
                    row = next(rows)
                except StopIteration:
                    return
                except apsw.Error as err:
                    self.damage = self.damage or f"{self.path.name}: {err}"
                    return
                yield int(row[0]), int(row[1]), bytes(row[2])
        except apsw.Error as err:
            self.damage = self.damage or f"{self.path.name}: {err}"
        finally:
            con.close()


# -- the reader ----------------------------------------------------------------------------------
class SalvageReader:
    """Complete messages of damaged MCAP/sqlite3 files (see the module docstring).

    Args:
        path: a ``.mcap``/``.db3`` file or a rosbag2 folder.
        typestore: rosbags typestore for deserialization (the Jazzy one).

    Raises:
        BagError: not an MCAP/sqlite3 file, or nothing at all could be read.
    """

    def __init__(self, path: Path, typestore: Any) -> None:
        self.path = Path(path)
        self.typestore = typestore
        self._files: list[Any] = []
        self._conn_by_key: dict[tuple[int, int], SalvageConnection] = {}
        self.connections: list[SalvageConnection] = []
        self._registered: set[str] = set()
        try:
            self._open()
        except BaseException:
            self.close()
            raise

    def _open(self) -> None:
        files = storage_files(self.path)
        if not files:
            raise BagError(f"{self.path} holds no .mcap or .db3 file")
        for f in files:
            self._files.append(_SqliteFile(f) if f.suffix.lower() == ".db3" else _McapFile(f))
        counts: dict[tuple[int, int], int] = {}
        self.last_good_ns = 0
        for n, f in enumerate(self._files):
            for cid, log_ns, _ in f.messages():
                counts[(n, cid)] = counts.get((n, cid), 0) + 1
                self.last_good_ns = max(self.last_good_ns, log_ns)
        by_topic: dict[str, int] = {}
        for n, f in enumerate(self._files):
            for cid, (topic, msgtype) in self._channels(f).items():
                by_topic.setdefault(topic, len(by_topic))
                conn = SalvageConnection(by_topic[topic], topic, msgtype, counts.get((n, cid), 0))
                self._conn_by_key[(n, cid)] = conn
        merged: dict[str, SalvageConnection] = {}
        for conn in self._conn_by_key.values():
            prev = merged.get(conn.topic)
            merged[conn.topic] = conn if prev is None else SalvageConnection(
                prev.id, prev.topic, prev.msgtype, prev.msgcount + conn.msgcount)
        self.connections = sorted(merged.values(), key=lambda c: c.id)
        if not any(c.msgcount for c in self.connections):
            detail = "; ".join(f.damage for f in self._files if f.damage) or "no messages"
            raise NothingSalvaged(f"nothing readable in {self.path}: {detail}", detail)
        expected, end_ns = _metadata(self.path)
        # Until when messages were lost: the latest the files or the metadata say (chunks after
        # the cut one may be lost whole; only metadata.yaml knows about them).
        until = [f.lost_until_ns for f in self._files if f.lost_until_ns is not None]
        if end_ns is not None:
            until.append(end_ns)
        detail = "; ".join(f.damage for f in self._files if f.damage)
        self.damage: Damage | None = None
        if detail:
            self.damage = Damage(detail, self.last_good_ns, max(until) if until else None,
                                 expected)

    def _channels(self, f: Any) -> dict[int, tuple[str, str]]:
        if isinstance(f, _SqliteFile):
            for msgtype, (enc, text) in f.definitions.items():
                self._register(msgtype, enc, text)
            return dict(f.topics)
        out = {}
        for cid, (topic, sid) in f.channels.items():
            name, enc, data = f.schemas.get(sid, ("", "", b""))
            self._register(name, enc, data.decode("utf-8", "replace"))
            out[cid] = (topic, name)
        return out

    def _register(self, msgtype: str, encoding: str, text: str) -> None:
        """Add a type the typestore lacks from the file's own definition (best effort)."""
        if not msgtype or msgtype in self.typestore.types or msgtype in self._registered:
            return
        self._registered.add(msgtype)
        try:
            from rosbags.typesys import get_types_from_msg

            if encoding in ("ros2msg", "msg") and text:
                self.typestore.register(get_types_from_msg(text, msgtype))
        except Exception:  # noqa: BLE001 - an unknown type only makes its messages unreadable
            pass

    def open(self) -> None:
        """Already open (``AnyReader`` compatibility)."""

    def messages(self, connections: Sequence[SalvageConnection] | None = None
                 ) -> Iterator[tuple[SalvageConnection, int, bytes]]:
        """(connection, log time ns, raw CDR) of every complete message, in file order."""
        wanted = None if connections is None else {c.topic for c in connections}
        for n, f in enumerate(self._files):
            for cid, log_ns, raw in f.messages():
                conn = self._conn_by_key.get((n, cid))
                if conn is not None and (wanted is None or conn.topic in wanted):
                    yield conn, log_ns, raw

    def deserialize(self, raw: bytes, msgtype: str) -> Any:
        return self.typestore.deserialize_cdr(raw, msgtype)

    def close(self) -> None:
        """Nothing to release: every file is opened per walk."""

    def __enter__(self) -> SalvageReader:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


"""Read bags as raw CDR messages, with rosbags.

A bag is any of: a rosbag2 folder with metadata.yaml (sqlite3 or mcap storage, split
into several files, metadata versions 4 to 9, zstd compression), a rosbag2 folder of
storage files without metadata.yaml, one .db3 or .mcap file, or a ROS 1 .bag file
(its messages converted to CDR). The storage files are the truth: topics, counts and
time window come from them, never from metadata.yaml, which is a hint (rosbags matches
its connection list by QoS text and yields nothing when metadata and storage disagree;
rosbag2's own split test bags promise a window their storage does not hold). Where the
metadata disagrees, `Bag.metadata_mismatch` says how. The count read is checked against
what the storage's index promises.
"""
import heapq
import re
from collections import Counter
from contextlib import ExitStack
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterable, Iterator, Protocol, Sequence

from rosbags.interfaces import (Connection, MessageDefinitionFormat, Qos, QosDurability,
                                QosReliability)
from rosbags.rosbag1 import Reader as Rosbag1Reader
from rosbags.rosbag2 import Reader as Rosbag2Reader
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

try:
    from compression import zstd
except ImportError:
    from backports import zstd

STORAGE_SUFFIXES = ('.mcap', '.db3')
ZSTD_MAGIC = b'\x28\xb5\x2f\xfd'


class BagError(RuntimeError):
    """A bag cannot be read, or yields other than what its metadata promises."""


@dataclass(frozen=True)
class BagMessage:
    topic: str
    msgtype: str          # e.g. 'sensor_msgs/msg/Image'
    t_ns: int             # receive time recorded in the bag
    raw: bytes            # CDR, as recorded (ROS 1 messages converted)


@dataclass(frozen=True)
class QosOffer:
    """The reliability and durability a publisher offers (or a subscriber requests)."""

    reliable: bool = True
    transient_local: bool = False


@dataclass(frozen=True)
class TopicInfo:
    topic: str
    msgtype: str
    count: int            # messages the bag's metadata (or storage index) promises
    offer: QosOffer       # what a replay publisher should offer, see replay_offer


def replay_offer(profiles: Sequence[Qos]) -> QosOffer:
    """The offer that stands in for the recorded publishers (rosbag2's rule).

    Their common reliability and durability when they all agree; the default offer
    (reliable, volatile) when none was recorded or they differ.
    """
    offers = {_offer(p) for p in profiles}
    return offers.pop() if len(offers) == 1 else QosOffer()


def record_request(profiles: Sequence[Qos]) -> QosOffer:
    """The subscription that matches every publisher (rosbag2's rule): reliable only if
    all offer reliable, transient local only if all offer it."""
    offers = [_offer(p) for p in profiles]
    return QosOffer(bool(offers) and all(o.reliable for o in offers),
                    bool(offers) and all(o.transient_local for o in offers))


def _offer(qos: Qos) -> QosOffer:
    return QosOffer(qos.reliability != QosReliability.BEST_EFFORT,
                    qos.durability == QosDurability.TRANSIENT_LOCAL)


class _Storage(Protocol):
    connections: list[Connection]

    def messages(self, connections: Sequence[Connection], start: int | None,
                 stop: int | None) -> Iterator[tuple[Connection, int, bytes]]: ...


@dataclass
class _Source:
    """One storage file: its reader and how its raw data becomes CDR."""

    file: Path
    storage: _Storage
    to_cdr: Callable[[Connection, bytes], bytes]


class Bag:
    """An open bag: `topics`, `start_ns`, `end_ns` (after the last message) and `messages()`,
    all as the storage holds them; `metadata_mismatch`: how metadata.yaml disagrees, or None.

    Raises BagError, naming the file, when the bag cannot be opened.
    """

    def __init__(self, path: Path | str) -> None:
        self.path = Path(path)
        self.topics: dict[str, TopicInfo] = {}
        self.start_ns = 0
        self.end_ns = 0
        self.metadata_mismatch: str | None = None
        self._sources: list[_Source] = []
        self._stack = ExitStack()
        try:
            self._open()
        except BagError:
            self.close()
            raise
        except Exception as err:
            self.close()
            raise BagError(f'{self.path}: cannot open bag: {err}') from err

    def __enter__(self) -> 'Bag':
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        self._stack.close()

    @property
    def message_count(self) -> int:
        return sum(t.count for t in self.topics.values())

    def messages(self, topics: Iterable[str] | None = None, start_ns: int | None = None,
                 stop_ns: int | None = None) -> Iterator[BagMessage]:
        """Yield the messages of `topics` (all if None) with start_ns <= t < stop_ns, in time
        order across the files of a split bag.

        Reading the whole bag (no bounds, or bounds around all of it) checks the count per
        topic against the storage's index and raises BagError on any difference, so an
        unreadable bag is never played as an empty or shortened stream.
        """
        wanted = set(self.topics) if topics is None else set(topics)
        streams = [_read(source, [c for c in source.storage.connections if c.topic in wanted],
                         start_ns, stop_ns) for source in self._sources]
        got: Counter[str] = Counter()
        for msg in heapq.merge(*streams, key=lambda m: m.t_ns):
            got[msg.topic] += 1
            yield msg
        whole = ((start_ns is None or start_ns <= self.start_ns)
                 and (stop_ns is None or stop_ns >= self.end_ns))
        if whole:
            short = {t: (got[t], self.topics[t].count) for t in sorted(wanted & set(self.topics))
                     if got[t] != self.topics[t].count}
            if short:
                detail = ', '.join(f'{t}: {n} of {m}' for t, (n, m) in short.items())
                raise BagError(f'{self.path}: the storage holds other than its index '
                               f'promises (messages read: {detail})')

    def _open(self) -> None:
        if not self.path.exists():
            raise BagError(f'{self.path}: no such file or folder')
        if self.path.is_dir() and (self.path / 'metadata.yaml').exists():
            self._open_rosbag2_folder()
        elif self.path.is_dir():
            files = sorted((f for f in self.path.iterdir() if f.suffix in STORAGE_SUFFIXES),
                           key=_split_index)
            if not files:
                raise BagError(f'{self.path}: neither metadata.yaml nor a .mcap/.db3 file')
            self._open_storage_files(files)
        elif self.path.suffix in STORAGE_SUFFIXES:
            self._open_storage_files([self.path])
        elif self.path.suffix == '.bag':
            self._open_rosbag1()
        else:
            raise BagError(f'{self.path}: not a bag (expected a folder, .mcap, .db3 or .bag)')

    def _opened(self, reader: Rosbag1Reader | Rosbag2Reader, culprit: Callable[[], Path],
                what: str = 'bag') -> Rosbag1Reader | Rosbag2Reader:
        """`reader` opened, to be closed with the bag; a BagError naming culprit() if not."""
        try:
            reader.open()
        except Exception as err:
            raise BagError(f'{culprit()}: cannot open {what}: {err}') from err
        self._stack.callback(reader.close)
        return reader

    def _open_rosbag2_folder(self) -> None:
        reader = self._opened(Rosbag2Reader(self.path), self._failing_file)
        storages = reader.storage.storages
        for storage in storages:
            self._sources.append(_Source(self.path / storage.path.name, storage, _cdr))
        self._set_topics([c for s in storages for c in s.connections],
                         min(s.metadata.start_time for s in storages),
                         max(s.metadata.end_time for s in storages))
        self.metadata_mismatch = self._mismatch(reader)

    def _mismatch(self, metadata: Rosbag2Reader) -> str | None:
        """How `metadata` (opened on metadata.yaml) disagrees with the storage, or None."""
        promised: Counter[str] = Counter()
        for c in metadata.connections:
            promised[c.topic] += c.msgcount
        held = {t: info.count for t, info in self.topics.items()}
        counts = [f'{t}: {promised[t]} in metadata, {held.get(t, 0)} in storage'
                  for t in sorted(set(promised) | set(held)) if promised[t] != held.get(t, 0)]
        window = ((metadata.start_time, metadata.end_time) if metadata.message_count else (0, 0))
        what = []
        if window != (self.start_ns, self.end_ns):
            what.append(f'time window [{window[0]}, {window[1]}) ns in metadata, '
                        f'[{self.start_ns}, {self.end_ns}) ns in storage')
        if counts:
            what.append('message counts ' + '; '.join(counts))
        if not what:
            return None
        return (f'{self.path}: metadata.yaml disagrees with the storage, which is read as the '
                f'truth: {"; ".join(what)}')

    def _failing_file(self) -> Path:
        """The storage file of a rosbag2 folder that cannot be opened on its own, if any."""
        for file in sorted(self.path.iterdir()):
            if file.suffix in STORAGE_SUFFIXES:
                try:
                    with Rosbag2Reader(file):
                        pass
                except Exception:
                    return file
        return self.path / 'metadata.yaml'

    def _open_storage_files(self, files: list[Path]) -> None:
        readers = []
        for file in files:
            reader = self._opened(Rosbag2Reader(file), lambda: file)   # called at once
            readers.append(reader)
            self._sources.append(_Source(file, reader, _cdr))
        self._set_topics([c for r in readers for c in r.connections],
                         min(r.start_time for r in readers), max(r.end_time for r in readers))

    def _open_rosbag1(self) -> None:
        reader = self._opened(Rosbag1Reader(self.path), lambda: self.path, 'ROS 1 bag')
        types = {}
        for conn in reader.connections:
            if conn.msgdef.format == MessageDefinitionFormat.MSG:
                types.update(get_types_from_msg(conn.msgdef.data, conn.msgtype))
        # ROS 1 headers carry a sequence number that ROS 2's do not: convert to ROS 2's.
        header = 'std_msgs/msg/Header'
        types[header] = get_typestore(Stores.ROS2_JAZZY).fielddefs[header]
        store = get_typestore(Stores.EMPTY)
        store.register(types)
        self._sources.append(_Source(
            self.path, reader, lambda conn, data: bytes(store.ros1_to_cdr(data, conn.msgtype))))
        offers = {c.topic: QosOffer(True, bool(c.ext.latching)) for c in reader.connections}
        self._set_topics(reader.connections, reader.start_time, reader.end_time, offers)

    def _set_topics(self, conns: list[Connection], start_ns: int, end_ns: int,
                    offers: dict[str, QosOffer] | None = None) -> None:
        counts: Counter[str] = Counter()
        for c in conns:
            counts[c.topic] += c.msgcount
        for c in conns:
            if c.topic not in self.topics:
                offer = offers[c.topic] if offers else replay_offer(
                    [q for x in conns if x.topic == c.topic for q in x.ext.offered_qos_profiles])
                self.topics[c.topic] = TopicInfo(c.topic, c.msgtype, counts[c.topic], offer)
        self.start_ns, self.end_ns = (start_ns, end_ns) if counts.total() else (0, 0)


def _read(source: _Source, conns: list[Connection], start_ns: int | None,
          stop_ns: int | None) -> Iterator[BagMessage]:
    """The messages of `conns` in one storage file; a BagError naming the file if it is corrupt."""
    if not conns:
        return
    n = 0
    try:
        for conn, t_ns, data in source.storage.messages(conns, start_ns, stop_ns):
            n += 1
            yield BagMessage(conn.topic, conn.msgtype, t_ns, source.to_cdr(conn, data))
    except Exception as err:
        raise BagError(f'{source.file}: corrupt bag after {n} of its messages: {err}') from err


def _cdr(conn: Connection, data: bytes) -> bytes:
    """Stored data as CDR: zstd-compressed messages (compression mode 'message') are
    recognised by their magic number, which CDR (its first byte is 0) never starts with."""
    return zstd.decompress(data) if data[:4] == ZSTD_MAGIC else bytes(data)


def _split_index(file: Path) -> tuple[str, int]:
    """Order the files of a split bag (name_0, name_1, ..., name_10) by their index."""
    match = re.fullmatch(r'(.*?)_?(\d+)', file.stem)
    return (match[1], int(match[2])) if match else (file.stem, -1)


def read_messages(path: Path | str, topics: Iterable[str] | None = None) -> Iterator[BagMessage]:
    """Yield the bag's messages in time order; raise BagError if it yields fewer than promised."""
    with Bag(path) as bag:
        yield from bag.messages(topics)

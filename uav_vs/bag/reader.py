"""Read rosbag2 files (sqlite3 or mcap) as raw CDR messages, with rosbags."""
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable, Iterator

from rosbags.rosbag2 import Reader


class BagError(RuntimeError):
    """A bag cannot be read, or yields other than what its metadata promises."""


@dataclass(frozen=True)
class BagMessage:
    topic: str
    msgtype: str          # e.g. 'sensor_msgs/msg/Image'
    t_ns: int             # receive time recorded in the bag
    raw: bytes            # CDR, as recorded


def read_messages(path: Path | str, topics: Iterable[str] | None = None) -> Iterator[BagMessage]:
    """Yield the bag's messages in time order; raise BagError if it yields fewer than promised."""
    path = Path(path)
    try:
        reader = Reader(path)
        reader.open()
    except Exception as err:
        raise BagError(f'{path}: cannot open bag: {err}') from err
    try:
        wanted = set(topics) if topics is not None else None
        conns = [c for c in reader.connections if wanted is None or c.topic in wanted]
        promised = sum(c.msgcount for c in conns)
        got = 0
        try:
            for conn, t_ns, raw in reader.messages(connections=conns):
                got += 1
                yield BagMessage(conn.topic, conn.msgtype, t_ns, bytes(raw))
        except Exception as err:
            raise BagError(f'{path}: corrupt bag after {got} messages: {err}') from err
        if got != promised:
            raise BagError(f'{path}: yielded {got} messages, metadata promises {promised}')
    finally:
        reader.close()

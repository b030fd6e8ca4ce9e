"""Write raw CDR messages to a rosbag2 (metadata version 9, as ROS 2 Jazzy writes it), with rosbags.

Each topic's message definition comes from rosbags' Jazzy type store; types it lacks
are read from the `share/<package>/msg/<Type>.msg` files of the installed message
packages (the ament prefixes, then this Python's prefix). The definition is stored as
rosbag2 stores it (ros2msg: the type's fields, then each type it uses after a line of
'=' and `MSG: <type>`), with `char` spelt `uint8`, the type rosidl gives it, and the
type hash stored beside it is the RIHS01 of that very definition, so readers that check
the hash against the definition (rosbags' AnyReader) accept it, and it equals the hash
rosidl gives the type.
"""
from collections import Counter
from pathlib import Path
from typing import Sequence

from rosbags.interfaces import Connection, Nodetype, Qos
from rosbags.interfaces.typing import Typesdict
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from uav_vs.bag.reader import BagError
from uav_vs.install_prefixes import install_prefixes

STORAGES = {'mcap': StoragePlugin.MCAP, 'sqlite3': StoragePlugin.SQLITE3}


class BagWriter:
    """A new rosbag2 folder at `path`; `close()` writes its metadata.yaml."""

    def __init__(self, path: Path | str, storage: str = 'mcap') -> None:
        self.path = Path(path)
        self.counts: Counter[str] = Counter()
        self._store = get_typestore(Stores.ROS2_JAZZY)
        try:
            self._writer = Writer(self.path, version=9, storage_plugin=STORAGES[storage])
            self._writer.open()
        except Exception as err:
            raise BagError(f'{self.path}: cannot create bag: {err}') from err

    def add_topic(self, topic: str, msgtype: str, offered: Sequence[Qos] = ()) -> Connection:
        """Register a topic with the QoS profiles its publishers offered; the connection's
        `digest` is the type hash stored (see the module's docstring)."""
        self._register(msgtype)
        msgdef = self._store.generate_msgdef(msgtype, ros_version=2)[0]
        return self._writer.add_connection(topic, msgtype, msgdef=msgdef,
                                           rihs01=definition_hash(msgdef, msgtype),
                                           offered_qos_profiles=offered)

    def write(self, conn: Connection, t_ns: int, raw: bytes) -> None:
        self._writer.write(conn, t_ns, raw)
        self.counts[conn.topic] += 1

    def close(self) -> None:
        self._writer.close()

    def _register(self, msgtype: str) -> None:
        """Add msgtype and the types it uses to the type store, from their .msg files."""
        if msgtype in self._store.fielddefs:
            return
        types = _char_as_uint8(get_types_from_msg(_msg_definition(msgtype), msgtype))
        self._store.register(types)
        for _, fields in types.values():
            for _, (kind, sub) in fields:
                if kind == Nodetype.NAME:
                    self._register(sub)
                elif kind in (Nodetype.ARRAY, Nodetype.SEQUENCE) and sub[0][0] == Nodetype.NAME:
                    self._register(sub[0][1])


def _msg_definition(msgtype: str) -> str:
    package, kind, name = msgtype.split('/')
    prefixes = install_prefixes()
    for prefix in prefixes:
        file = prefix / 'share' / package / kind / f'{name}.msg'
        if file.is_file():
            return file.read_text()
    raise BagError(f'no message definition for {msgtype} (no share/{package}/{kind}/{name}.msg '
                   f'in {", ".join(map(str, prefixes))})')


def definition_hash(msgdef: str, msgtype: str) -> str:
    """The RIHS01 hash of `msgtype` as the ros2msg definition `msgdef` describes it."""
    store = get_typestore(Stores.EMPTY)
    store.register(get_types_from_msg(msgdef, msgtype))
    return store.hash_rihs01(msgtype)


def _char_as_uint8(types: Typesdict) -> Typesdict:
    """`char` fields and constants as `uint8`: rosidl's type for a ROS 2 .msg `char` (the
    same byte on the wire), which rosbags would otherwise hash as a type of its own."""
    def base(desc: tuple) -> tuple:
        kind, rest = desc
        if kind == Nodetype.BASE and rest[0] == 'char':
            return kind, ('uint8', rest[1])
        if kind in (Nodetype.ARRAY, Nodetype.SEQUENCE):
            return kind, (base(rest[0]), rest[1])
        return desc

    return {name: ([(c, 'uint8' if t == 'char' else t, v) for c, t, v in consts],
                   [(f, base(desc)) for f, desc in fields])
            for name, (consts, fields) in types.items()}

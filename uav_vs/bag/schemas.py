"""ROS 2 message and service definitions as text: the `ros2msg` schemas that rosbag2's MCAP
storage records and the Foxglove WebSocket protocol advertises.

A type's schema is its `.msg` file as installed (share/<package>/msg/<Type>.msg under a
prefix of AMENT_PREFIX_PATH), followed by the file of every type it uses, each once,
after a line of 80 `=` and `MSG: <package>/<Type>`: what foxglove_bridge sends and what
Foxglove, Lichtblick and rosbags parse. A service's request and response are the two
halves of its `.srv` file (`<type>_Request`, `<type>_Response`), with the same tail.
Without the file (a prefix that holds no definitions), a type rosbags knows is written
from rosbags' own definition of ROS 2 Jazzy.
"""
import os
from functools import lru_cache
from pathlib import Path

from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from rosbags.typesys.base import Nodetype

SEPARATOR = '=' * 80


class SchemaError(LookupError):
    """No definition of a type was found; str() names it and where it was looked for."""


def message_schema(msgtype: str) -> str:
    """'geometry_msgs/msg/PoseStamped' -> its ros2msg schema text."""
    return _with_dependencies(msgtype, _message_text(msgtype))


def service_schemas(srvtype: str) -> tuple[str, str]:
    """'std_srvs/srv/SetBool' -> the ros2msg schemas of its request and its response."""
    text = _definition_file(srvtype, 'srv')
    if text is None:
        raise SchemaError(f'{srvtype}: no .srv file in {_prefixes()}')
    lines = text.splitlines(keepends=True)
    cut = next((k for k, line in enumerate(lines) if line.strip() == '---'), None)
    if cut is None:
        raise SchemaError(f'{srvtype}: its .srv file has no --- line')
    request, response = ''.join(lines[:cut]), ''.join(lines[cut + 1:])
    return (_with_dependencies(f'{srvtype}_Request', request),
            _with_dependencies(f'{srvtype}_Response', response))


def _with_dependencies(name: str, text: str) -> str:
    parts, seen = [text.rstrip('\n') + '\n' if text.strip() else ''], {name}
    pending = _used_types(name, text)
    while pending:
        dep = pending.pop(0)
        if dep in seen:
            continue
        seen.add(dep)
        dep_text = _message_text(dep)
        package, _, type_name = dep.split('/')
        parts.append(f'{SEPARATOR}\nMSG: {package}/{type_name}\n{dep_text.rstrip(chr(10))}\n')
        pending.extend(_used_types(dep, dep_text))
    return ''.join(parts)


def _used_types(name: str, text: str) -> list[str]:
    """The message types `text` (the definition of `name`) has fields of, in order."""
    if not text.strip():
        return []
    package, _, type_name = name.split('/')      # a service's halves resolve as messages
    [(_, fields)] = get_types_from_msg(text, f'{package}/msg/{type_name}').values()
    used = []
    for _, (kind, desc) in fields:
        if kind in (Nodetype.ARRAY, Nodetype.SEQUENCE):
            kind, desc = desc[0]
        if kind == Nodetype.NAME:
            used.append(desc)
    return used


@lru_cache(maxsize=None)
def _message_text(msgtype: str) -> str:
    text = _definition_file(msgtype, 'msg')
    if text is not None:
        return text
    store = _jazzy()
    if msgtype not in store.fielddefs:
        raise SchemaError(f'{msgtype}: no .msg file in {_prefixes()} and not a ROS 2 Jazzy type')
    return store.generate_msgdef(msgtype, ros_version=2)[0].split(f'{SEPARATOR}\n')[0]


def _definition_file(typename: str, kind: str) -> str | None:
    package, _, name = typename.split('/')
    for prefix in _prefixes():
        path = Path(prefix) / 'share' / package / kind / f'{name}.{kind}'
        if path.is_file():
            return path.read_text()
    return None


def _prefixes() -> list[str]:
    return [p for p in os.environ.get('AMENT_PREFIX_PATH', '').split(os.pathsep) if p]


@lru_cache(maxsize=1)
def _jazzy():
    return get_typestore(Stores.ROS2_JAZZY)

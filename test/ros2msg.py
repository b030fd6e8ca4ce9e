"""Read a `ros2msg` schema back into rosbags types, as Foxglove and Lichtblick read the
ones foxglove_node advertises: the inverse of uav_vs.bag.schemas, for the tests."""
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from uav_vs.bag.schemas import SEPARATOR


def schema_types(name: str, schema: str) -> dict:
    """Every type the schema of `name` ('pkg/Type' or 'pkg/msg/Type') defines, as rosbags
    parses it: full type name -> field definitions."""
    first, *rest = schema.split(f'\n{SEPARATOR}\n') if schema.strip() else ['']
    package, type_name = name.split('/')[0], name.split('/')[-1]
    types = get_types_from_msg(first, f'{package}/msg/{type_name}') if first.strip() else {}
    for part in rest:
        header, _, text = part.partition('\n')
        dep_package, dep_name = header.removeprefix('MSG: ').split('/')
        types.update(get_types_from_msg(text, f'{dep_package}/msg/{dep_name}'))
    return types


def cdr_decoder(name: str, schema: str):
    """bytes -> the message of type `name`, decoded with the types its schema defines."""
    types = schema_types(name, schema)
    store = get_typestore(Stores.EMPTY)
    store.register(types)
    type_name = name.split('/')[-1]
    [typename] = [t for t in types if t.endswith('/' + type_name)]
    return lambda data: store.deserialize_cdr(data, typename)

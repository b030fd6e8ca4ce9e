"""What the layout that ships for Foxglove and Lichtblick (config/foxglove/uav_vs.json, the
classic `configById` + `layout` form both import) asks of the graph: the topics its
panels read and the message fields its plots read (docs/live_view.md)."""
import json
from pathlib import Path

from uav_vs.vision.ground_config import default_config_path

LAYOUT = default_config_path('foxglove/uav_vs.json')
# The same for a slow link, with foxglove_node given config/foxglove_slow_link.yaml too.
SLOW_LINK = default_config_path('foxglove/uav_vs_slow_link.json')


def load_layout(path: Path = LAYOUT) -> dict:
    return json.loads(Path(path).read_text())


def panels(tree: dict | str) -> list[str]:
    """The panel ids of a layout tree, left to right."""
    if isinstance(tree, str):
        return [tree]
    return panels(tree['first']) + panels(tree['second'])


def references(layout: dict) -> list[tuple[str, str, tuple[str, ...]]]:
    """(panel id, topic, field path) for every topic a panel reads; the path is empty
    where the panel takes whole messages. A 3D or image panel also reads /tf and
    /tf_static. A panel type this does not know raises ValueError."""
    refs = []
    for panel, config in layout['configById'].items():
        kind = panel.split('!')[0]
        if kind in ('3D', 'Image'):
            refs += [(panel, '/tf', ()), (panel, '/tf_static', ())]
            mode = config.get('imageMode', {})
            refs += [(panel, mode[key], ()) for key in ('imageTopic', 'calibrationTopic')
                     if mode.get(key)]
            refs += [(panel, topic, ()) for topic in mode.get('annotations', {})]
            refs += [(panel, topic, ()) for topic, shown in config.get('topics', {}).items()
                     if shown.get('visible')]
        elif kind == 'Plot':
            for path in config['paths']:
                topic, *fields = path['value'].split('.')
                refs.append((panel, topic, tuple(fields)))
        elif kind == 'DiagnosticSummary':
            refs.append((panel, config['topicToRender'], ()))
        else:
            raise ValueError(f'{panel}: a panel type uav_vs.flight.live_view does not know')
    return refs


def layout_topics(layout: dict) -> list[str]:
    """Every topic the layout reads, sorted."""
    return sorted({topic for _, topic, _ in references(layout)})

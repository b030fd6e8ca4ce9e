"""graph/live_view: what watching a flight in Foxglove costs the graph, and what a viewer
on a slow link receives (docs/live_view.md).

The `setpoints` scenario flown as graph/latency flies it, without a viewer and then with
foxglove_node (and frames_node, as `make demo VIEW=1` runs them) and one client that
watches: `layout`, the topics of the layout that ships (config/foxglove/uav_vs.json: the
cameras' JPEG streams, annotations, poses, commands, TF, diagnostics); `everything`, every
topic, the cameras' raw frames too; `slow_link`, the slow link's layout
(config/foxglove/uav_vs_slow_link.json) with foxglove_node given
config/foxglove_slow_link.yaml: each camera's JPEG stream re-encoded at half size,
quality 50, 5 Hz, its annotations scaled alike. The client is the official protocol
client on Node.js (tools/foxglove_probe), counting what it receives. Targets: image
stamp -> cmd_vel with the viewer within 10 % of the flight without it (median), the slow
link under 2 Mbit/s.
"""
import json
import re
import shutil
import socket
import subprocess
import tempfile
import threading
import time
from pathlib import Path

import numpy as np
import yaml

from bench.common import report
from uav_vs.flight.live_view import LAYOUT, SLOW_LINK, layout_topics, load_layout
from uav_vs.flight.report import command_latencies
from uav_vs.flight.scenario import SETPOINTS, Configs, fly, free_port
from uav_vs.vision.ground_config import default_config_path

PROBE = Path(__file__).resolve().parents[1] / 'tools' / 'foxglove_probe'
LATENCY_TARGET = 1.10          # with a viewer / without, median image stamp -> cmd_vel
SLOW_LINK_TARGET_MBIT_S = 2.0


class Viewer:
    """The probe, started once foxglove_node takes connections on `port`, subscribed to
    every topic `pattern` (a regular expression) matches; it stops when the server goes."""

    def __init__(self, node: str, folder: Path, port: int, pattern: str) -> None:
        self.result: dict = {}
        spec = {'url': f'ws://127.0.0.1:{port}', 'watch': pattern, 'timeout_s': 900,
                'settle_s': 0.5}
        self.thread = threading.Thread(target=self._run, args=(node, folder, port, spec),
                                       daemon=True)
        self.thread.start()

    def _run(self, node: str, folder: Path, port: int, spec: dict) -> None:
        while True:
            try:
                socket.create_connection(('127.0.0.1', port), timeout=0.2).close()
                break
            except OSError:
                time.sleep(0.2)
        done = subprocess.run([node, str(folder / 'probe.mjs'), json.dumps(spec)],
                              capture_output=True, text=True, stdin=subprocess.DEVNULL)
        self.result = json.loads(done.stdout) if done.stdout else {'error': done.stderr}

    def wait(self) -> dict:
        self.thread.join(60)
        return self.result


def flight(tmp: Path, name: str, viewer: tuple[str, Path, str, Path] | None):
    """Fly `name` as `make demo` does (its bag recorded: the simulated cameras encode
    JPEG); with `viewer` (node, probe folder, topics pattern, foxglove_node's params file
    but for the port), watched."""
    configs, watching = Configs(), None
    if viewer is not None:
        node, folder, pattern, params_file = viewer
        port = free_port()
        params = yaml.safe_load(params_file.read_text())
        params['/**']['ros__parameters']['foxglove']['port'] = port
        (tmp / f'{name}.yaml').write_text(yaml.safe_dump(params))
        configs = Configs(foxglove=tmp / f'{name}.yaml',
                          frames=default_config_path('frames.yaml'))
        watching = Viewer(node, folder, port, pattern)
    log = fly(SETPOINTS, tmp / name, configs)
    return log, watching.wait() if watching else None


def main() -> None:
    node, npm = shutil.which('node'), shutil.which('npm')
    if node is None or npm is None:
        print('graph/live_view: skipped, Node.js and npm not found (the Foxglove protocol '
              'client runs on them; Debian: apt install nodejs npm)', flush=True)
        return
    with tempfile.TemporaryDirectory(prefix='uav_vs_live_view_') as tmp:
        tmp = Path(tmp)
        folder = tmp / 'probe'
        folder.mkdir()
        for name in ('package.json', 'package-lock.json', 'probe.mjs'):
            shutil.copy(PROBE / name, folder / name)
        subprocess.run([npm, 'ci', '--no-audit', '--no-fund', '--loglevel=error'],
                       cwd=folder, check=True, stdin=subprocess.DEVNULL)
        base, _ = flight(tmp, 'alone', None)
        full, slow = (default_config_path(f) for f in ('foxglove.yaml',
                                                        'foxglove_slow_link.yaml'))
        layout, slow_layout = ('|'.join(re.escape(t) for t in layout_topics(load_layout(f)))
                               for f in (LAYOUT, SLOW_LINK))
        runs = {case: flight(tmp, case, (node, folder, pattern, params))
                for case, pattern, params in (('layout', layout, full),
                                              ('everything', '.*', full),
                                              ('slow_link', slow_layout, slow))}
    alone = command_latencies(base)
    for case, (log, seen) in runs.items():
        watched = command_latencies(log)
        seconds = max(seen.get('seconds', 0), 1e-9)
        topics = seen.get('watched', {})
        report('graph', f'graph/live_view/{case}', watched, 'the same flight, no viewer',
               alone, median_ratio=round(float(np.median(watched) / np.median(alone)), 3),
               target_ratio=LATENCY_TARGET, topics=len(topics),
               messages=sum(c['messages'] for c in topics.values()),
               mbit_s=round(seen.get('bytesRead', 0) * 8e-6 / seconds, 3),
               **({'target_mbit_s': SLOW_LINK_TARGET_MBIT_S,
                   'kbit_s_per_topic': {t: round(c['bytes'] * 8e-3 / seconds, 1)
                                        for t, c in sorted(topics.items())}}
                  if case == 'slow_link' else {}),
               failure=log.failure or base.failure or seen.get('error') or None)


if __name__ == '__main__':
    main()

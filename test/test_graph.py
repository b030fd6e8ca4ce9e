"""uav_vs.graph.stop: the processes stop one at a time, last started first."""
import subprocess
import sys
import time

from uav_vs import graph

# Records when SIGINT came, then exits 0; prints 'ready' once its handler is in place.
SCRIPT = """
import signal, sys, time
def stop(*_):
    open(sys.argv[1], 'w').write(repr(time.monotonic()))
    sys.exit(0)
signal.signal(signal.SIGINT, stop)
print('ready', flush=True)
while True:
    time.sleep(1)
"""


def test_stop_takes_the_processes_down_one_at_a_time_last_started_first(tmp_path):
    marks = [tmp_path / f'{k}.stopped' for k in range(3)]
    procs = [subprocess.Popen([sys.executable, '-c', SCRIPT, str(m)], stdout=subprocess.PIPE,
                              text=True) for m in marks]
    for p in procs:
        assert p.stdout.readline().strip() == 'ready'
    t0 = time.monotonic()
    assert graph.stop(procs) == [0, 0, 0]
    times = [float(m.read_text()) for m in marks]
    assert times[2] < times[1] < times[0]
    # Each was stopped only once the one before it had gone.
    assert times[1] - times[2] >= graph.SETTLE_S and times[0] - times[1] >= graph.SETTLE_S
    assert all(t >= t0 for t in times)
    for p in procs:
        p.stdout.close()

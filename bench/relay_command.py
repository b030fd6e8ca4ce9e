"""The relay's per-command path on its own: `relay/send_velocity`.

Session.send_velocity (checks, limiter, send-rate bookkeeping, MAVLink encode, UDP send)
to the simulated vehicle, 5,000 calls timed one by one, every one sent (the send-rate
limit set out of reach). Reference: `limit_velocity` alone, the limiter inside it.
This module runs unchanged on trees older than the send-rate limit, so
`python -m bench.compare REV relay` times this path before and after a change.
"""
import dataclasses
import time

import numpy as np

from bench.common import report
from uav_vs.autopilot.session import Limits, Session, SessionConfig, limit_velocity
from uav_vs.sim.mavlink_vehicle import MavlinkVehicle, VehicleConfig

SUITE = 'relay'
CALLS, WARMUP = 5000, 1000


def commands(n: int) -> list[tuple[float, float, float]]:
    """Commands within the default limits, a little different each call."""
    return [(0.3 + 1e-4 * (k % 7), -0.2, 0.1) for k in range(n)]


def per_call(fn, args: list) -> np.ndarray:
    """fn(*a) for each a in args, timed one by one; ms, the warm-up calls left out."""
    out = np.empty(len(args))
    for k, a in enumerate(args):
        t0 = time.perf_counter()
        fn(*a)
        out[k] = (time.perf_counter() - t0) * 1e3
    return out[WARMUP:]


def main() -> None:
    fields = {f.name for f in dataclasses.fields(SessionConfig)}
    with MavlinkVehicle(VehicleConfig(connection='udpin:127.0.0.1:0', ready_delay=0.2)) as vehicle:
        config = dict(connection=f'udpout:127.0.0.1:{vehicle.address[1]}', rates={},
                      command_timeout=5.0)
        if 'max_send_rate' in fields:
            config['max_send_rate'] = 1e6      # every call sends
        with Session(SessionConfig(**config)) as session:
            session.wait_connected(10.0)
            cmds = commands(WARMUP + CALLS)
            ours = per_call(lambda v: session.send_velocity(v, 0.1), [(v,) for v in cmds])
            limits = Limits()
            ref = per_call(lambda v: limit_velocity(v, 0.1, limits), [(v,) for v in cmds])
            report(SUITE, 'relay/send_velocity', ours, 'limit_velocity alone', ref)


if __name__ == '__main__':
    main()

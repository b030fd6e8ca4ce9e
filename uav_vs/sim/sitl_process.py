"""Start ArduCopter SITL for a closed-loop flight, in a network namespace of its own.

The SITL binary binds its MAVLink ports on 0.0.0.0. Run as root, `enter_loopback_namespace`
moves this process (its calling thread, and every process it starts from then on) into a
new network namespace that has nothing but loopback, so neither the SITL nor the ROS
graph flying it can be reached from, or reach, any other interface. `ArduCopterSitl`
then starts the binary there: SERIAL0 (tcp 5760 + 10 * instance) for the relay,
SERIAL1 (+2) for the SIM_STATE truth, SERIAL2 (+3) for `warm_up`.

Booting with GPS, ArduCopter SITL is ready to arm ~42 s after its start: EKF3 uses the GPS
only once its gyro biases are learnt, in simulated time. `warm_up` lets that time run
`WARM_UP_SPEEDUP` times faster (SIM_SPEEDUP, which the SITL takes at run time) while the
vehicle stands on the ground, and back to real time before anything of the graph talks to
it: nothing of the autopilot's behaviour changes, only the wait (~5 s instead of ~42 s).

The binary is `UAV_VS_ARDUPILOT_SITL`, else `../shared/sitl/ardupilot/arducopter`
beside the checkout; its default parameters are the `copter.parm` beside it (ArduPilot's
Tools/autotest/default_params/copter.parm).
"""
import os
import socket
import subprocess
import time
from pathlib import Path

from pymavlink import mavutil

from uav_vs.sim import netns

SITL_ENV = 'UAV_VS_ARDUPILOT_SITL'
BESIDE_CHECKOUT = (Path(__file__).resolve().parents[3] / 'shared' / 'sitl' / 'ardupilot'
                   / 'arducopter')
HOME_LLA = (-35.363261, 149.165230, 584.0)   # lat, lon deg, AMSL m (ArduPilot's CMAC)
HOME = f'{HOME_LLA[0]},{HOME_LLA[1]},{HOME_LLA[2]:g},353'   # ... and heading, deg
HOW_TO_GET = (f'set {SITL_ENV} to an ArduCopter SITL binary (build ArduPilot for the sitl '
              'board: ardupilot.org, "Setting up SITL on Linux", then ./waf copter) or put it '
              f'at {BESIDE_CHECKOUT}; or start SITL yourself and give its connection')
WARM_UP_SPEEDUP = 10.0
# Ready to arm: the pre-arm checks pass and EKF3 has an absolute horizontal position (and
# its prediction), as the relay's `prearm_ok` and the mission's wait see it.
EKF_ABSOLUTE = (mavutil.mavlink.EKF_POS_HORIZ_ABS | mavutil.mavlink.EKF_PRED_POS_HORIZ_ABS)


def find_binary() -> Path | None:
    """The ArduCopter SITL binary: UAV_VS_ARDUPILOT_SITL, else the one beside the checkout."""
    named = os.environ.get(SITL_ENV)
    if named:
        return Path(named)
    return BESIDE_CHECKOUT if BESIDE_CHECKOUT.is_file() else None


def enter_loopback_namespace(name: str) -> None:
    """Create network namespace `name` (loopback up, nothing else) and move into it.

    Needs root (ip netns). Call it before any thread or node starts: only the calling
    thread moves, and what it starts afterwards inherits the namespace.
    """
    if os.geteuid() != 0:
        raise PermissionError('a loopback-only network namespace for SITL needs root; '
                              'start SITL yourself and give its connection instead')
    netns.add(name)
    netns.enter(name)


class ArduCopterSitl:
    """The SITL binary run by `with` in `workdir` (its log: sitl-<instance>.log)."""

    def __init__(self, binary: Path, workdir: Path, instance: int = 0, speedup: float = 1.0,
                 extra_params: tuple[Path, ...] = ()) -> None:
        if not binary.is_file():
            raise FileNotFoundError(f'ArduCopter SITL {binary} not found: {HOW_TO_GET}')
        self.binary, self.workdir, self.instance = binary, workdir, instance
        self.speedup, self.params = speedup, (binary.parent / 'copter.parm', *extra_params)
        self.proc: subprocess.Popen | None = None

    @property
    def serial_ports(self) -> tuple[int, int, int]:
        base = 5760 + 10 * self.instance
        return base, base + 2, base + 3

    @property
    def log_path(self) -> Path:
        return self.workdir / f'sitl-{self.instance}.log'

    def __enter__(self) -> 'ArduCopterSitl':
        self.workdir.mkdir(parents=True, exist_ok=True)
        with open(self.log_path, 'wb') as log:
            self.proc = subprocess.Popen(
                [str(self.binary), '--model', 'quad', '--speedup', f'{self.speedup:g}',
                 '--defaults', ','.join(str(p.resolve()) for p in self.params),
                 f'-I{self.instance}', '-w', '--serial0', 'tcp:0', '--home', HOME],
                cwd=self.workdir, stdout=log, stderr=subprocess.STDOUT)
        return self

    def warm_up(self, timeout: float = 60.0) -> float | None:
        """Run the SITL WARM_UP_SPEEDUP times faster until it is ready to arm, then at its
        own speed again; the seconds of simulated time that took (None: not ready within
        `timeout` s of wall time, and the mission waits for it as without a warm-up)."""
        conn = self._connect(self.serial_ports[2], timeout)
        try:
            for msg_id in (mavutil.mavlink.MAVLINK_MSG_ID_SYS_STATUS,
                           mavutil.mavlink.MAVLINK_MSG_ID_EKF_STATUS_REPORT,
                           mavutil.mavlink.MAVLINK_MSG_ID_SYSTEM_TIME):
                conn.mav.command_long_send(1, 1, mavutil.mavlink.MAV_CMD_SET_MESSAGE_INTERVAL,
                                           0, msg_id, 200_000, 0, 0, 0, 0, 0)
            self._set_speedup(conn, WARM_UP_SPEEDUP)
            prearm = ekf = False
            boot_ms = None
            deadline = time.monotonic() + timeout
            while not (prearm and ekf) and time.monotonic() < deadline:
                msg = conn.recv_match(type=['SYS_STATUS', 'EKF_STATUS_REPORT', 'SYSTEM_TIME'],
                                      blocking=True, timeout=1.0)
                if msg is None:
                    continue
                kind = msg.get_type()
                if kind == 'SYS_STATUS':
                    prearm = bool(msg.onboard_control_sensors_health
                                  & mavutil.mavlink.MAV_SYS_STATUS_PREARM_CHECK)
                elif kind == 'EKF_STATUS_REPORT':
                    ekf = msg.flags & EKF_ABSOLUTE == EKF_ABSOLUTE
                else:
                    boot_ms = msg.time_boot_ms
            return boot_ms / 1000.0 if prearm and ekf and boot_ms is not None else None
        finally:
            self._set_speedup(conn, self.speedup)
            conn.close()

    def _connect(self, port: int, timeout: float):
        deadline = time.monotonic() + timeout
        while True:     # the port opens a moment after the start
            try:
                socket.create_connection(('127.0.0.1', port), timeout=1.0).close()
                break
            except OSError:
                if time.monotonic() > deadline or self.proc.poll() is not None:
                    raise RuntimeError(f'ArduCopter SITL never served tcp {port}: see '
                                       f'{self.log_path}') from None
                time.sleep(0.2)
        conn = mavutil.mavlink_connection(f'tcp:127.0.0.1:{port}', source_system=254,
                                          autoreconnect=False)
        if conn.wait_heartbeat(timeout=timeout) is None:
            raise RuntimeError(f'no heartbeat from ArduCopter SITL on tcp {port}: see '
                               f'{self.log_path}')
        return conn

    @staticmethod
    def _set_speedup(conn, speedup: float, timeout: float = 5.0) -> None:
        """SIM_SPEEDUP, sent until the SITL echoes the value."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            conn.mav.param_set_send(1, 1, b'SIM_SPEEDUP', speedup,
                                    mavutil.mavlink.MAV_PARAM_TYPE_REAL32)
            echo = conn.recv_match(type='PARAM_VALUE', blocking=True, timeout=0.5)
            if echo is not None and echo.param_id == 'SIM_SPEEDUP' \
                    and abs(echo.param_value - speedup) < 1e-3:
                return
        raise RuntimeError(f'ArduCopter SITL did not take SIM_SPEEDUP {speedup:g}')

    def __exit__(self, *exc) -> None:
        if self.proc is None or self.proc.poll() is not None:
            return
        self.proc.terminate()
        deadline = time.monotonic() + 10.0     # it was seen to take over 1.5 s
        while self.proc.poll() is None and time.monotonic() < deadline:
            time.sleep(0.1)
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait()

"""Start ArduCopter SITL for a closed-loop flight, in a network namespace of its own.

The SITL binary binds its MAVLink ports on 0.0.0.0. Run as root, `enter_loopback_namespace`
moves this process (its calling thread, and every process it starts from then on) into a
new network namespace that has nothing but loopback, so neither the SITL nor the ROS
graph flying it can be reached from, or reach, any other interface. `ArduCopterSitl`
then starts the binary there: SERIAL0 (tcp 5760 + 10 * instance) for the relay,
SERIAL1 (+2) for the SIM_STATE truth.

The binary is `UAV_VS_ARDUPILOT_SITL`, else `../shared/sitl/ardupilot/arducopter`
beside the checkout; its default parameters are the `copter.parm` beside it (ArduPilot's
Tools/autotest/default_params/copter.parm).
"""
import os
import subprocess
import time
from pathlib import Path

from uav_vs.sim import netns

SITL_ENV = 'UAV_VS_ARDUPILOT_SITL'
BESIDE_CHECKOUT = (Path(__file__).resolve().parents[3] / 'shared' / 'sitl' / 'ardupilot'
                   / 'arducopter')
HOME_LLA = (-35.363261, 149.165230, 584.0)   # lat, lon deg, AMSL m (ArduPilot's CMAC)
HOME = f'{HOME_LLA[0]},{HOME_LLA[1]},{HOME_LLA[2]:g},353'   # ... and heading, deg
HOW_TO_GET = (f'set {SITL_ENV} to an ArduCopter SITL binary (build ArduPilot for the sitl '
              'board: ardupilot.org, "Setting up SITL on Linux", then ./waf copter) or put it '
              f'at {BESIDE_CHECKOUT}; or start SITL yourself and give its connection')


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

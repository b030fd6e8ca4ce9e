"""Pose filter (uav_vs.control.pose_filter): one update per measurement, next to filterpy's
KalmanFilter doing the same linear update (predict + update) in the same process.

fusion/pose_update: a ground pose applied in stamp order; fusion/pose_update_late: one
arriving 0.1 s late among 30 Hz poses (put in place and the 3 later ones applied again);
fusion/odometry_update: the autopilot's odometry (the non-linear body-velocity part);
fusion/estimate: the state predicted to a publishing time. The target is 0.2 ms per
update.
"""
import numpy as np
from filterpy.common import Q_discrete_white_noise
from filterpy.kalman import KalmanFilter

from bench.common import report, timeit
from uav_vs.control.pose_filter import (FilterParams, PoseFilter, odometry_measurement,
                                        pose_measurement)

SUITE = 'fusion'
DT = 1 / 30
POSE_R = np.diag([0.03 ** 2] * 3 + [0.02 ** 2])


def measurements(rng, count: int, source: str = 'ground', start: float = 0.0) -> list:
    return [pose_measurement(source, start + k * DT, rng.normal(0, 0.03, 3) + [0.5 * k * DT, 0, 1],
                             rng.normal(0, 0.02), POSE_R) for k in range(count)]


def filterpy_filter(params: FilterParams) -> KalmanFilter:
    kf = KalmanFilter(dim_x=8, dim_z=4)
    kf.F = np.eye(8)
    kf.F[:3, 3:6], kf.F[6, 7] = np.eye(3) * DT, DT
    kf.Q = np.zeros((8, 8))
    for axis in range(3):
        kf.Q[np.ix_([axis, 3 + axis], [axis, 3 + axis])] = Q_discrete_white_noise(
            2, DT, params.accel_sigma ** 2)
    kf.Q[np.ix_([6, 7], [6, 7])] = Q_discrete_white_noise(2, DT, params.yaw_accel_sigma ** 2)
    kf.H = np.zeros((4, 8))
    kf.H[:3, :3], kf.H[3, 6] = np.eye(3), 1.0
    kf.R = POSE_R
    return kf


def main() -> None:
    rng = np.random.default_rng(0)
    params = FilterParams()
    stream = measurements(rng, 2000)
    f = PoseFilter(params)
    k = iter(range(10 ** 9))
    ms = timeit(lambda: f.add(stream[next(k)]), 1500, warmup=10)
    kf = filterpy_filter(params)
    z = iter(m.z for m in stream * 2)

    def reference():
        kf.predict()
        kf.update(next(z))
    report(SUITE, 'fusion/pose_update', ms, 'filterpy KalmanFilter', timeit(reference, 1500))

    late = PoseFilter(params)
    ground = measurements(rng, 2000)
    onboard = measurements(rng, 2000, 'onboard', start=DT / 2)
    j = iter(range(10 ** 9))

    def add_late():
        n = next(j)
        late.add(onboard[n])
        if n >= 3:
            late.add(ground[n - 3])               # 0.1 s late: three later poses again
    report(SUITE, 'fusion/pose_update_late', timeit(add_late, 1500, warmup=10) / 2)

    odo = PoseFilter(params)
    cov = np.diag([0.1] * 3 + [0.01] + [0.01] * 3 + [0.01])
    stamps = iter(np.arange(0, 100, 0.02))
    ms = timeit(lambda: odo.add(odometry_measurement(
        'autopilot', next(stamps), [0, 0, 1], 0.3, [0.5, 0, 0], 0.0, cov)), 1500)
    report(SUITE, 'fusion/odometry_update', ms)
    newest = f.estimate(stream[1509].stamp)
    report(SUITE, 'fusion/estimate', timeit(lambda: f.estimate(newest.stamp + 0.01), 1500))


if __name__ == '__main__':
    main()

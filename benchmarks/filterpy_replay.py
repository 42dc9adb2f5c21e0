"""
The plain script a user would write with filterpy to replay a train log (the baseline).

    python benchmarks/filterpy_replay.py INPUT.csv OUTPUT.csv

INPUT: a header, then t [s], z_position [m]. OUTPUT: t, position, velocity, their
variances, the same predicted 2 s ahead, and the NIS of the fix (y S⁻¹ y, filterpy's
``y`` and ``SI``): the 10 columns of ``kf-train replay --preset train``, from the
same model (seed 000: F = [[1, dt], [0, 1]], Q = 0, R = 1, x0 = [0, 5], P0 = I, the
prior holding at t = 0). ``make bench`` row 7 times it
against ``kf-train replay``, process start-up included.
"""

import sys

from filterpy.kalman import KalmanFilter
import numpy as np

HORIZON_S = 2.0


def main(argv) -> int:
    """Replay argv[0] into argv[1]."""
    source, target = argv
    data = np.loadtxt(source, delimiter=',', skiprows=1, ndmin=2)
    kf = KalmanFilter(dim_x=2, dim_z=1)
    kf.x = np.array([0.0, 5.0])
    kf.P = np.eye(2)
    kf.H = np.array([[1.0, 0.0]])
    kf.R = np.array([[1.0]])
    kf.Q = np.zeros((2, 2))
    ahead = np.array([[1.0, HORIZON_S], [0.0, 1.0]])
    out = np.empty((data.shape[0], 10))
    previous = 0.0
    for k, (t, z) in enumerate(data[:, :2]):
        kf.F = np.array([[1.0, t - previous], [0.0, 1.0]])
        kf.predict()
        kf.update(z)
        previous = t
        x_ahead = ahead @ kf.x
        P_ahead = ahead @ kf.P @ ahead.T
        out[k] = (t, kf.x[0], kf.x[1], kf.P[0, 0], kf.P[1, 1], x_ahead[0], x_ahead[1],
                  P_ahead[0, 0], P_ahead[1, 1], kf.y @ kf.SI @ kf.y)
    np.savetxt(target, out, delimiter=',', comments='',
               header='t,position,velocity,var_position,var_velocity,predicted_position,'
                      'predicted_velocity,var_predicted_position,var_predicted_velocity,nis')
    return 0


if __name__ == '__main__':
    sys.exit(main(sys.argv[1:]))

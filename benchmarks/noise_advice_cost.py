"""
What the suggested q in ``/diagnostics`` costs the estimator node, per measurement.

The node's session (:class:`kf_train.ros.session.EstimatorSession`, what its callbacks
run; preset train, gate off) is fed a random-force train at 10 Hz (``rows``
measurements, q = 2 while the node runs q = 0, so the suggestion is shown), once with
``noise_suggestion_window:=0`` (off)
and once with each window, with a diagnostics status every 10 measurements (1 s, the
node's default period). It prints, per window:

* the time per measurement callback, with and without the suggestion (the append);
* the time per diagnostics status, and of the statuses that recompute the suggestion
  (every window measurements), its mean and worst;
* the total added per measurement: (time with − time without) / measurements, the
  recomputations included.

Best of ``--repeat`` runs of each, to take the other processes on a shared machine out.
Run: ``.venv/bin/python benchmarks/noise_advice_cost.py [--rows 3000]``. It prints
figures; nothing is asserted (test/unit/test_noise_advice.py holds the assertions).
"""

import argparse
import time

from kf_train.ros import noise_advice
from kf_train.ros.estimator_params import load_estimator_config
from kf_train.ros.session import EstimatorSession, Measurement
from kf_train.sim import white_noise_acceleration_scenario

NS = 1_000_000_000
EPOCH_NS = 1_700_000_000 * NS
DIAGNOSTICS_EVERY = 10


def run(window: int, stamps, z):
    """Return (s in measurement callbacks, s per status list, refresh count) of one run."""
    now = [EPOCH_NS]
    # The train's KF (the default preset, rail, has no q to suggest), gate off.
    session = EstimatorSession(
        load_estimator_config([], ['preset:=train', 'gate_probability:=1.0',
                                   f'noise_suggestion_window:={window}']),
        lambda: now[0] / NS)
    measuring, statuses = 0.0, []
    for k, (stamp_ns, value) in enumerate(zip(stamps, z)):
        now[0] = stamp_ns
        message = Measurement(stamp_ns, 'odom', value, 1.0)
        start = time.perf_counter()
        session.on_measurement(message, stamp_ns)
        measuring += time.perf_counter() - start
        if (k + 1) % DIAGNOSTICS_EVERY == 0:
            start = time.perf_counter()
            session.diagnostics(stamp_ns)
            statuses.append(time.perf_counter() - start)
    return measuring, statuses


def main() -> None:
    """Print the figures."""
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--rows', type=int, default=3000)
    parser.add_argument('--repeat', type=int, default=3)
    parser.add_argument('--windows', type=int, nargs='+', default=[100, 300, 1000])
    args = parser.parse_args()
    scenario = white_noise_acceleration_scenario(2.0, 1.0, args.rows, seed=1)
    stamps = [EPOCH_NS + round(t * NS) for t in scenario.t_s.tolist()]
    z = scenario.z[:, 0].tolist()

    def best(window):
        runs = [run(window, stamps, z) for _ in range(args.repeat)]
        return min(runs, key=lambda r: r[0] + sum(r[1]))

    off_measuring, off_statuses = best(0)
    off_total = off_measuring + sum(off_statuses)
    n = args.rows
    print(f'{n} measurements at 10 Hz, a status every {DIAGNOSTICS_EVERY}; best of '
          f'{args.repeat}')
    print(f'off: {off_measuring / n * 1e6:.1f} µs per measurement callback, '
          f'{sum(off_statuses) / len(off_statuses) * 1e6:.0f} µs per status')
    for window in args.windows:
        measuring, statuses = best(window)
        refresh_every = max(1, window // noise_advice.REFRESH_FRACTION)
        slow = sorted(statuses)[-max(1, n // refresh_every):]
        added = (measuring + sum(statuses) - off_total) / n
        print(f'window {window}: {measuring / n * 1e6:.1f} µs per measurement callback '
              f'(+{(measuring - off_measuring) / n * 1e6:.1f}); recomputing statuses '
              f'{len(slow)}: mean {sum(slow) / len(slow) * 1e3:.1f} ms, worst '
              f'{max(slow) * 1e3:.1f} ms; added per measurement, all included: '
              f'{added * 1e6:.0f} µs ({added * 10 * 100:.2f} % of a core at 10 Hz)')


if __name__ == '__main__':
    main()

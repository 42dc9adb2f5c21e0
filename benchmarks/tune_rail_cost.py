"""
What ``kf-train tune --preset rail`` costs: one pass of K settings, and a whole fit.

A simulated metro run (``--seed``, ``--rows`` fixes at 10 Hz, σ = 1 m) is given to
:func:`kf_train.batch.rail_log_likelihoods` with K = 1, 7 and 19 settings (one setting:
one IMM run; 7 and 19: the stencils of the fit's Newton steps with two and three
noises), and to the whole fit (:func:`kf_train.tune.rail_fit.fit_rail_noise`, the
acceleration and command noises and R). For comparison it times the node's own classes
(RailModel.predict/update, one setting). Best of ``--repeat`` for the passes.
Run: ``.venv/bin/python benchmarks/tune_rail_cost.py [--rows 6000]``. It prints
figures; nothing is asserted (test/unit/test_tune_rail.py holds the assertions).
"""

import argparse
import time

from kf_train.batch import rail_log_likelihoods, RailNoise, Segment
from kf_train.filters import RailModel, RailModelParameters
from kf_train.sim.rail import rail_scenario
from kf_train.tune import fit_rail_noise
import numpy as np


def _node_run(segment: Segment, params: RailModelParameters) -> float:
    """Return the seconds of one run of the node's RailModel over the segment."""
    model = RailModel(params)
    z, t = segment.z[:, 0], segment.t_s
    R = np.array([[1.0]])
    began = time.perf_counter()
    state = model.first_estimate(z[0], 1.0)
    for k in range(1, z.shape[0]):
        state = model.predict(state, float(t[k] - t[k - 1]))
        state, _ = model.update(state, z[k], R)
    return time.perf_counter() - began


def main() -> None:
    """Print the figures."""
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--rows', type=int, default=6000)
    parser.add_argument('--seed', type=int, default=100)
    parser.add_argument('--repeat', type=int, default=2)
    args = parser.parse_args()
    scenario, _ = rail_scenario(seed=args.seed, family='metro')
    segment = Segment(scenario.t_s[:args.rows], scenario.z[:args.rows])
    base = RailModelParameters()
    print(f'rail run metro seed {args.seed}, {segment.t_s.shape[0]} fixes')
    node = min(_node_run(segment, base) for _ in range(args.repeat))
    print(f"  node's RailModel, 1 setting: {node:.2f} s")
    for count in (1, 7, 19):
        settings = [RailNoise(1e-4 * (1.0 + 0.01 * i)) for i in range(count)]
        best = []
        for _ in range(args.repeat):
            began = time.perf_counter()
            rail_log_likelihoods(base, [segment], settings)
            best.append(time.perf_counter() - began)
        print(f'  one pass, K = {count:2d} settings: {min(best):.2f} s')
    rows = segment.t_s.shape[0] - 1
    start = RailNoise(base.acceleration_noise, base.command_noise, base.capability_noise, 1.0)
    fit = fit_rail_noise(lambda s: rail_log_likelihoods(base, [segment], s).log_likelihood,
                         ['acceleration_noise', 'command_noise', 'measurement_variance'],
                         start, start, rows)
    print(f'  whole fit (q_a, q_l, R): {fit.seconds:.1f} s, {fit.passes} passes, '
          f'{fit.evaluations} settings; estimates ' + ', '.join(
              f'{e.parameter.symbol} {e.value:.4g} [{e.low:.4g}, {e.high:.4g}]'
              for e in fit.estimates))


if __name__ == '__main__':
    main()

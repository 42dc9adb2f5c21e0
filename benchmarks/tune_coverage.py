"""
Do ``kf-train tune``'s 95 % intervals hold the true noises? 50 seeded runs of known noises.

Each run is drawn from the rail IMM's own model (:func:`kf_train.sim.sample_rail_model`:
regimes at the model's rates, its entry transformation, N(0, Q(dt)) per regime, the
position measured with σ = 1 m at 10 Hz) with q_a = 3e-3, q_ℓ = 3e-4 m²/s⁵ and R = 1 m²,
and the fit (:func:`kf_train.tune.fit_rail_noise`, the rail likelihood of
:func:`kf_train.batch.rail_log_likelihoods`) estimates the three from the shipped
defaults. The script prints, per noise, the share of runs whose interval holds the truth
(the issue's target: >= 90 %), the share "compatible with 0", and the fit's time.

The rail scenario's realistic GNSS runs (``rail_gnss_model`` receiver) have no true q_a
or q_ℓ: their motion is not the IMM's, and their error is not white, so there is no
truth there for an interval to cover; their figures are in benchmarks/tune_real_logs.py.

    PYTHONPATH=. python benchmarks/tune_coverage.py [--runs 50] [--rows 3000]

Figures only, no assertion.
"""

import argparse
import dataclasses
import sys

from kf_train.batch import rail_log_likelihoods, RailNoise, Segment
from kf_train.filters import RailModelParameters
from kf_train.sim import sample_rail_model
from kf_train.tune import fit_rail_noise
import numpy as np

TRUTH = {'acceleration_noise': 3e-3, 'command_noise': 3e-4, 'measurement_variance': 1.0}


def main() -> int:
    """Run the seeded fits; print the coverage."""
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[1])
    parser.add_argument('--runs', type=int, default=50)
    parser.add_argument('--rows', type=int, default=3000)
    args = parser.parse_args()
    base = RailModelParameters()
    truth = dataclasses.replace(base, acceleration_noise=TRUTH['acceleration_noise'],
                                command_noise=TRUTH['command_noise'])
    names = list(TRUTH)
    start = RailNoise(base.acceleration_noise, base.command_noise, base.capability_noise, 1.0)
    inside = dict.fromkeys(names, 0)
    at_zero = dict.fromkeys(names, 0)
    seconds = []
    for seed in range(args.runs):
        t, z = sample_rail_model(truth, args.rows, seed)
        segment = Segment(t, z[:, None])
        fit = fit_rail_noise(
            lambda s: rail_log_likelihoods(base, [segment], s).log_likelihood,
            names, start, start, rows=args.rows - 1)
        seconds.append(fit.seconds)
        for e in fit.estimates:
            n = e.parameter.name
            inside[n] += int(e.identified and e.low <= TRUTH[n] <= e.high)
            at_zero[n] += int(e.low == 0.0)
        print(f'seed {seed}: ' + ', '.join(
            f'{e.parameter.symbol} {e.value:.3g} [{e.low:.3g}, {e.high:.3g}]'
            for e in fit.estimates) + f' ({fit.seconds:.1f} s, {fit.passes} passes)',
            flush=True)
    print(f'\n{args.runs} runs of {args.rows} fixes drawn from the rail IMM (q_a 3e-3, '
          f'q_l 3e-4, R 1); 95 % intervals; fit {np.median(seconds):.1f} s median\n')
    print('| noise | truth | interval holds it | compatible with 0 |')
    print('|---|---|---|---|')
    for n in names:
        print(f'| {n} | {TRUTH[n]:g} | {100 * inside[n] / args.runs:.0f} % | '
              f'{100 * at_zero[n] / args.runs:.0f} % |')
    return 0


if __name__ == '__main__':
    sys.exit(main())

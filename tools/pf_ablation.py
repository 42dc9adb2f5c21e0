"""
Print docs/filters.md's ablation of the particle filter on the range-bearing seed.

Each row switches parts of :class:`kf_train.filters.regularised_pf.RegularisedParticleFilter`
on or off (or runs the bootstrap filter), over the same seeded Monte-Carlo runs as
``kf-train compare`` (scenario seed r, initial estimate and filter seed derived from
(seed, r) the same way):

    .venv/bin/python tools/pf_ablation.py [--runs 100] [--particles 2000] [--initial preset]
"""

import argparse
import math
import sys
import time

from kf_train.batch import time_steps_s
from kf_train.evaluate import anees_bounds, derived_seed, nees
from kf_train.filters import ParticleFilter, psd_factor, RegularisedParticleFilter
from kf_train.presets import load_preset
from kf_train.sim import scenario_for_preset
import numpy as np

VARIANTS = (
    ('bootstrap', ParticleFilter, {}),
    ('bootstrap + roughening 0.2', ParticleFilter, {'roughening': 0.2}),
    ('measurement draw only', RegularisedParticleFilter,
     {'tempering': False, 'kernel': 'gordon', 'roughening': 0.0, 'metropolis': False}),
    ('measurement draw + roughening 0.2', RegularisedParticleFilter,
     {'tempering': False, 'kernel': 'gordon', 'metropolis': False}),
    ('measurement draw + kernel + MH', RegularisedParticleFilter, {'tempering': False}),
    ('measurement draw + tempering + kernel', RegularisedParticleFilter, {'metropolis': False}),
    ('measurement draw + tempering + roughening + MH', RegularisedParticleFilter,
     {'kernel': 'gordon'}),
    ('tempering + kernel + MH (prior draw)', RegularisedParticleFilter,
     {'initialise_from_measurement': False}),
    ('pf: all (Gaussian kernel)', RegularisedParticleFilter, {}),
    ('pf: all, Epanechnikov kernel', RegularisedParticleFilter, {'kernel': 'epanechnikov'}),
)


def run_variant(cls, kwargs, runs, particles, initial, seed=0):
    """Return (RMSE [m], mean ANEES, rows in the 99% band, µs per row, counters)."""
    preset = load_preset('range-bearing')
    G0 = psd_factor('P0', preset.initial_covariance, 4)
    squared, nees_rows, seconds, counters = [], [], 0.0, {}
    for r in range(runs):
        scenario = scenario_for_preset('range-bearing', seed + r)
        x0 = preset.initial_state
        if initial == 'sampled':
            rng = np.random.default_rng(derived_seed(seed, r, 1))
            x0 = scenario.truth0 + G0 @ rng.standard_normal(4)
        start = time.perf_counter()
        pf = cls(preset.model, x0, preset.initial_covariance, n_particles=particles,
                 seed=derived_seed(seed, r, 2), **kwargs)
        x, P = [], []
        for k, dt in enumerate(time_steps_s(scenario.t_s)):
            pf.predict(dt)
            pf.update(scenario.z[k])
            x.append(pf.mean)
            P.append(pf.covariance)
        seconds += time.perf_counter() - start
        for key, value in getattr(pf, 'counters', {}).items():
            counters[key] = counters.get(key, 0) + value
        errors = np.array(x) - scenario.truth
        squared.append(errors[:, 0] ** 2 + errors[:, 2] ** 2)
        nees_rows.append(nees(errors, np.array(P)))
    anees = np.mean(nees_rows, axis=0)
    low, high = anees_bounds(runs, 4)
    return (math.sqrt(np.mean(squared)), float(anees.mean()),
            float(np.mean((anees >= low) & (anees <= high))),
            1e6 * seconds / np.size(squared), counters)


def main() -> int:
    """Print the table."""
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--runs', type=int, default=100)
    parser.add_argument('--particles', type=int, default=2000)
    parser.add_argument('--initial', choices=('sampled', 'preset'), default='sampled')
    args = parser.parse_args()
    print(f'range-bearing, {args.runs} runs, N = {args.particles}, initial {args.initial}')
    print('| variant | RMSE pos [m] | mean ANEES | rows in 99% | µs/row | MH accepted |')
    print('|---|---|---|---|---|---|')
    for name, cls, kwargs in VARIANTS:
        rmse, anees, inside, us, counters = run_variant(cls, kwargs, args.runs,
                                                        args.particles, args.initial)
        proposed = counters.get('moves_proposed', 0)
        accepted = (f"{counters['moves_accepted'] / proposed:.0%}"
                    if proposed and kwargs.get('metropolis', True) else '–')
        print(f'| {name} | {rmse:.4g} | {anees:.4g} | {inside:.0%} | {us:.0f} | {accepted} |',
              flush=True)
    return 0


if __name__ == '__main__':
    sys.exit(main())

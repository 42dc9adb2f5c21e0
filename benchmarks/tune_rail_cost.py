"""
What ``kf-train tune --preset rail`` costs: one pass of K settings, by engine, and a whole fit.

A simulated metro run (``--seed``, lasting ``--rows`` fixes at 10 Hz, σ = 1 m, stamps
jittered by ±2 ms so that every step has a new dt) is given to
:func:`kf_train.batch.rail_log_likelihoods` as the node runs it (the learned scale on
R, the χ² gate at 0.9999) with K = 1, 9 and 27 settings, by the
compiled engine (numba, ``kf_train.filters.rail_likelihood_kernel``) and by the numpy
reference (on ``--numpy-rows`` of them: it costs ~0.5 ms a row); then the whole fit
(:func:`kf_train.tune.rail_fit.fit_rail_noise`, the acceleration and command noises
and R, on ``--fit-rows``). Best of ``--repeat`` for the passes; the compiled kernel is
loaded (or compiled) before the clock starts. It prints figures; nothing is asserted
(test/unit/test_rail_likelihood_node.py holds the engines to each other and to the node).
Run: ``.venv/bin/python benchmarks/tune_rail_cost.py [--rows 30000]``.

Measured 2026-11-28 10:41 UTC (2-core machine shared with other sessions, load ~1),
30,000 fixes: numba 0.19 s (K = 1), 0.74 s (K = 9), 2.5 s (K = 27); numpy on 2000 fixes
546, 82 and 38 µs per row and setting; the whole fit on 6000 fixes 3.4 s (docs/rail.md).
"""

import argparse
import dataclasses
import time

from kf_train.batch import rail_log_likelihoods, RailNoise, Segment
from kf_train.filters import numba_available, RailModelParameters
from kf_train.sim.rail import family_parameters, rail_scenario
from kf_train.tune import fit_rail_noise
import numpy as np

GATE = 15.136705226623606         # χ²(1) at 0.9999, the node's default gate


def _segment(seed: int, rows: int) -> Segment:
    """Return a metro run of ``seed`` lasting ``rows`` fixes at 10 Hz, stamps jittered."""
    parameters = dataclasses.replace(family_parameters('metro', seed),
                                     duration_s=rows / 10.0 + 1.0)
    scenario, _ = rail_scenario(seed=seed, parameters=parameters)
    t = scenario.t_s[:rows]
    t = t + np.random.default_rng(seed).uniform(-0.002, 0.002, t.shape[0])
    return Segment(t, scenario.z[:rows])


def _pass_s(base, segment, count: int, engine: str, repeat: int) -> float:
    """Return the best seconds of one pass of ``count`` settings as the node runs them."""
    settings = [RailNoise(1e-4 * (1.0 + 0.01 * i)) for i in range(count)]
    best = []
    for _ in range(repeat):
        began = time.perf_counter()
        rail_log_likelihoods(base, [segment], settings, adaptation=base.adaptation(),
                             gate_threshold=GATE, engine=engine)
        best.append(time.perf_counter() - began)
    return min(best)


def main() -> None:
    """Print the figures."""
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--rows', type=int, default=30000)
    parser.add_argument('--numpy-rows', type=int, default=2000)
    parser.add_argument('--fit-rows', type=int, default=6000)
    parser.add_argument('--seed', type=int, default=100)
    parser.add_argument('--repeat', type=int, default=2)
    args = parser.parse_args()
    base = RailModelParameters()
    segment = _segment(args.seed, args.rows)
    engines = [('numba', segment)] if numba_available() else []
    engines.append(('numpy', Segment(segment.t_s[:args.numpy_rows],
                                     segment.z[:args.numpy_rows])))
    if numba_available():      # load (or compile) the kernel before timing
        rail_log_likelihoods(base, [Segment(segment.t_s[:50], segment.z[:50])],
                             [RailNoise()], engine='numba')
    print(f"metro run seed {args.seed}, jittered stamps; the node's likelihood "
          '(learned scale on R, gate 0.9999)')
    for engine, data in engines:
        rows = data.t_s.shape[0] - 1
        for count in (1, 9, 27):
            seconds = _pass_s(base, data, count, engine, args.repeat)
            print(f'  {engine:5s} {rows + 1:6d} fixes, K = {count:2d}: {seconds:7.3f} s, '
                  f'{1e6 * seconds / (rows * count):7.2f} µs per row per setting')
    fit_segment = Segment(segment.t_s[:args.fit_rows], segment.z[:args.fit_rows])
    start = RailNoise(base.acceleration_noise, base.command_noise, base.capability_noise, 1.0)
    fit = fit_rail_noise(lambda s: rail_log_likelihoods(base, [fit_segment], s).log_likelihood,
                         ['acceleration_noise', 'command_noise', 'measurement_variance'],
                         start, start, fit_segment.t_s.shape[0] - 1)
    print(f'  whole fit (q_a, q_l, R; fixed R, no gate, auto engine) on {args.fit_rows} '
          f'fixes: {fit.seconds:.1f} s, {fit.passes} passes, {fit.evaluations} settings; '
          'estimates ' + ', '.join(f'{e.parameter.symbol} {e.value:.4g} [{e.low:.4g}, '
                                   f'{e.high:.4g}]' for e in fit.estimates))


if __name__ == '__main__':
    main()

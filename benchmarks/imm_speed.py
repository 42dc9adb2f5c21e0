"""
µs per measurement of the rail IMM: before (the mode-by-mode original) and now (stacked).

Runs the default rail model over a seeded metro run (σ = 1 m at 10 Hz, dt = 0.1 s) and
times, per measurement, the IMM prediction to the measurement, the update, and the 2-s
prediction ahead that the live node publishes with every estimate. "before" is the
original algorithm of branch rail2, kept as test/imm_reference.py (the oracle of
test/unit/test_imm_stack.py); "now" is kf_train.filters.rail_model. Also timed: the
same steps through kf_train.estimator's (x, P) adapter (IMMModel), which the streaming
estimator uses.

The machine is shared, so each figure is the best of several blocks of consecutive
measurements (the least disturbed one), and the largest difference between the two
tracks is printed beside it. A second table times each step again from one state (after
60 s of the run), as the best of 150 repeats of 20 calls: the figure least disturbed by
other processes. Prints figures only, never asserts a time.

    .venv/bin/python benchmarks/imm_speed.py [--rows 3000] [--block 50]
"""

import argparse
import os
import sys
import time
import timeit

from kf_train.estimator.imm_model import IMMModel
from kf_train.filters.rail_model import RailModel, STATE_NAMES
from kf_train.sim.rail import rail_scenario
import numpy as np

HORIZON_S = 2.0
TEST_DIR = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), 'test')


def _reference_model():
    """Return the original algorithm, kept in the test folder as the tests' oracle."""
    sys.path.insert(0, TEST_DIR)
    from imm_reference import ReferenceRailModel
    return ReferenceRailModel()


def _time_model(model, t, z, block: int):
    """Return best-block µs per (predict, update, ahead) and the last 2-s predictions."""
    state = model.first_estimate(float(z[0]))
    best = [np.inf, np.inf, np.inf]
    spent = [0.0, 0.0, 0.0]
    ahead = np.empty(t.size)
    clock = time.perf_counter
    for k in range(1, t.size):
        dt = float(t[k] - t[k - 1])
        start = clock()
        state = model.predict(state, dt)
        middle = clock()
        state, _ = model.update(state, float(z[k]))
        end = clock()
        x_ahead, _ = model.predict_ahead(state, HORIZON_S)
        done = clock()
        ahead[k] = x_ahead[0]
        spent[0] += middle - start
        spent[1] += end - middle
        spent[2] += done - end
        if k % block == 0:
            best = [min(b, s / block * 1e6) for b, s in zip(best, spent)]
            spent = [0.0, 0.0, 0.0]
    return best, ahead


def _time_adapter(model, t, z, block: int, fused: bool = False) -> float:
    """
    Return best-block µs per predict + update + 2-s prediction through IMMModel.

    ``fused``: IMMModel.predict_update, what the streaming estimator calls for an
    in-order measurement (no combined (x, P) between the prediction and the update);
    else predict, then update.
    """
    adapter = IMMModel(model, [[1.0, 0, 0, 0, 0, 0]], [[1.0]], STATE_NAMES)
    state = model.first_estimate(float(z[0]))
    x, P = model.estimate(state)
    R = np.array([[1.0]])
    best, spent = np.inf, 0.0
    for k in range(1, t.size):
        start = time.perf_counter()
        dt = float(t[k] - t[k - 1])
        if fused:
            x, P, _ = adapter.predict_update(x, P, dt, np.array([z[k]]), R)
        else:
            x, P = adapter.predict(x, P, dt)
            x, P, _ = adapter.update(x, P, np.array([z[k]]), R)
        adapter.predict_ahead(x, P, HORIZON_S)
        spent += time.perf_counter() - start
        if k % block == 0:
            best, spent = min(best, spent / block * 1e6), 0.0
    return best


def _time_steps(model, z, settle: int = 600):
    """Return best-of-repeats µs of (predict, update, ahead) from the state after ``settle``."""
    state = model.first_estimate(float(z[0]))
    for k in range(1, settle):
        state, _ = model.update(model.predict(state, 0.1), float(z[k]))
    predicted = model.predict(state, 0.1)
    calls = (lambda: model.predict(state, 0.1), lambda: model.update(predicted, float(z[settle])),
             lambda: model.predict_ahead(state, HORIZON_S))
    return [min(timeit.repeat(call, number=20, repeat=150)) / 20 * 1e6 for call in calls]


def main(argv=None) -> int:
    """Time both implementations and print the table."""
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--rows', type=int, default=3000, help='measurements per run')
    parser.add_argument('--block', type=int, default=50, help='measurements per block')
    args = parser.parse_args(argv)
    scenario, _ = rail_scenario(11, 'metro')
    t, z = scenario.t_s[:args.rows], scenario.z[:args.rows, 0]
    before, ahead_before = _time_model(_reference_model(), t, z, args.block)
    now, ahead_now = _time_model(RailModel(), t, z, args.block)
    adapter = _time_adapter(RailModel(), t, z, 10)
    fused = _time_adapter(RailModel(), t, z, 10, fused=True)
    print(f'rail IMM, {t.size} measurements of a metro run, dt = 0.1 s; µs per measurement, '
          f'best block of {args.block}')
    print(f'{"":22}{"predict":>10}{"update":>10}{"2-s ahead":>11}{"total":>10}')
    for name, figures in (('before (rail2)', before), ('now (stacked)', now)):
        print(f'{name:22}' + ''.join(f'{f:10.1f}' for f in figures[:2]) +
              f'{figures[2]:11.1f}{sum(figures):10.1f}')
    print(f'speed-up: {sum(before) / sum(now):.1f}x; through IMMModel (estimator adapter): '
          f'{adapter:.1f} µs per measurement, {fused:.1f} µs with predict_update (what the '
          'estimator runs; best blocks of 10)')
    print('from one state (after 60 s), best of 150 x 20 calls:')
    steady = [_time_steps(model, z) for model in (_reference_model(), RailModel())]
    for name, figures in zip(('before (rail2)', 'now (stacked)'), steady):
        print(f'{name:22}' + ''.join(f'{f:10.1f}' for f in figures[:2]) +
              f'{figures[2]:11.1f}{sum(figures):10.1f}')
    print(f'speed-up: {sum(steady[0]) / sum(steady[1]):.1f}x')
    print(f'largest difference of the 2-s predicted positions: '
          f'{np.max(np.abs(ahead_now[1:] - ahead_before[1:])):.2e} m')
    return 0


if __name__ == '__main__':
    sys.exit(main())

"""
Score 2-s predictions on rail runs: RMSE and 2σ coverage after a warm-up, run by run.

A filter is anything with ``predict(dt_s)``, ``update(z)`` and
``predict_ahead(horizon_s) -> (x, P)`` whose first state is the position; a *maker*
``make(z0_m)`` returns one started at the first measurement. :func:`track` runs it
over a scenario (predict to each sample, update, predict the horizon ahead) and
:func:`score` compares each prediction with the exact truth at t + horizon_s, from
``warmup_s`` on. :func:`hindsight_best` tries every configuration of a grid on one
run and keeps the best: what a tuner who knows the run could reach, the bar the
default (fixed, never tuned per run) has to beat.

Nothing here imports a reference library; ``benchmarks/rail_eval.py`` brings
filterpy's filters as makers.
"""

import time
from typing import Callable, Iterable, List, NamedTuple, Sequence, Tuple

from kf_train.sim.rail import rail_scenario, RailRun
from kf_train.sim.scenarios import Scenario
import numpy as np

WARMUP_S = 10.0
"""Predictions made before this time after the start are not scored [s]."""
HORIZON_S = 2.0
"""How far ahead the predictions are scored [s]."""
EVALUATION_SEEDS = tuple(range(100, 108))
"""Seeds of the evaluation runs: never used to choose the defaults (0-9 were)."""


class RunCase(NamedTuple):
    """One rail run to evaluate on."""

    family: str
    seed: int
    scenario: Scenario
    run: RailRun

    @property
    def label(self) -> str:
        """Return e.g. 'metro-100'."""
        return f'{self.family}-{self.seed}'


class Track(NamedTuple):
    """A filter's predictions over a scenario."""

    t_s: np.ndarray
    """Times the predictions were made at (N,) [s]."""
    mean_m: np.ndarray
    """Predicted position at t_s + horizon_s (N,) [m]."""
    variance_m2: np.ndarray
    """Its variance (N,) [m²]."""
    update_s: float
    """Mean wall time of one predict + update [s]."""
    ahead_s: float
    """Mean wall time of one predict_ahead [s]."""


class Score(NamedTuple):
    """How good a track's predictions were."""

    rmse_m: float
    coverage: float
    """Fraction of predictions whose 2σ band held the truth."""
    count: int
    """Number of predictions scored."""


def run_cases(families: Sequence[str] = ('metro', 'regional'),
              seeds: Iterable[int] = EVALUATION_SEEDS) -> List[RunCase]:
    """Return the runs of every family for every seed (white noise σ = 1 m at 10 Hz)."""
    cases = []
    for family in families:
        for seed in seeds:
            scenario, run = rail_scenario(seed, family, gnss_model='white')
            cases.append(RunCase(family, int(seed), scenario, run))
    return cases


def track(make: Callable, scenario: Scenario, horizon_s: float = HORIZON_S) -> Track:
    """Run a filter over a scenario; predict horizon_s ahead after every sample."""
    t = scenario.t_s
    z = scenario.z[:, 0]
    count = t.shape[0]
    mean = np.empty(count)
    variance = np.empty(count)
    filt = make(float(z[0]))
    update_time = ahead_time = 0.0
    for k in range(count):
        if k:
            start = time.perf_counter()
            filt.predict(float(t[k] - t[k - 1]))
            filt.update(float(z[k]))
            update_time += time.perf_counter() - start
        start = time.perf_counter()
        x, P = filt.predict_ahead(horizon_s)
        ahead_time += time.perf_counter() - start
        mean[k] = x[0]
        variance[k] = P[0, 0]
    return Track(t.copy(), mean, variance, update_time / max(count - 1, 1),
                 ahead_time / count)


def score(result: Track, run: RailRun, warmup_s: float = WARMUP_S,
          horizon_s: float = HORIZON_S) -> Score:
    """Return RMSE and 2σ coverage of the predictions made from warmup_s on."""
    t = result.t_s
    scored = (t >= t[0] + warmup_s - 1e-9) & (t + horizon_s <= run.parameters.duration_s + 1e-9)
    truth = run.state_at(t[scored] + horizon_s).position_m
    error = result.mean_m[scored] - truth
    std = np.sqrt(np.maximum(result.variance_m2[scored], 0.0))
    return Score(float(np.sqrt(np.mean(error ** 2))), float(np.mean(np.abs(error) <= 2.0 * std)),
                 int(scored.sum()))


def hindsight_best(maker_for: Callable, grid: Sequence, case: RunCase,
                   horizon_s: float = HORIZON_S) -> Tuple[object, Score, Track]:
    """Return (configuration, score, track) of the lowest RMSE over ``grid`` on one run."""
    best = None
    for config in grid:
        result = track(maker_for(config), case.scenario, horizon_s)
        result_score = score(result, case.run, horizon_s=horizon_s)
        if best is None or result_score.rmse_m < best[1].rmse_m:
            best = (config, result_score, result)
    if best is None:
        raise ValueError('the grid is empty')
    return best


def format_table(header: Sequence[str], rows: Sequence[Sequence]) -> str:
    """Return a Markdown table."""
    lines = ['| ' + ' | '.join(header) + ' |', '|' + '---|' * len(header)]
    for row in rows:
        lines.append('| ' + ' | '.join(str(cell) for cell in row) + ' |')
    return '\n'.join(lines)

"""
Is a tuned setting better where it was not fitted? ``kf-train tune``'s hold-out and verdicts.

* :func:`split_holdout` cuts each segment at 75 % of its time span (by default): the
  fit sees the first part, the rest is held out. Deterministic (no draw): the held-out
  part is the latest, as the tuned setting will meet later data;
* :func:`score_setting` runs the estimator node's own :class:`StreamEstimator` (the
  node's defaults: χ² gate, lock-out, learned noise scale, out-of-sequence window)
  over every segment from its start, as ``kf-train replay`` would, and scores the
  2-s predictions made in the held-out windows (the filter warm, as in reality)
  against the later fix (:mod:`kf_train.evaluate.later_fix`) and, where the segment
  has it, against the truth;
* the node's rail IMM runs compiled there whenever numba is installed (as the fit's
  likelihood does), without the node's opt-in (KF_TRAIN_JIT), numpy otherwise
  (``jit``). The compiled model is the numpy reference's equations in numba loops, held
  to it at a norm-wise relative 1e-9 over random regimes, rewinds and speed updates
  (test/unit/test_rail_fast.py): the scores can differ from a numpy node run only at
  rounding level, far below the report's digits and WORSE_TOLERANCE (a gate decision
  flips only for a NIS within rounding of the threshold);
* :func:`model_verdict` says in plain words when the innovations' NIS or whiteness
  (:func:`kf_train.batch.nis_consistency`) shows that the model does not describe
  the data, and names the likely cause.
"""

import dataclasses
import math
import os
import tempfile
from typing import Iterator, List, NamedTuple, Optional, Sequence, Tuple, Union

from kf_train.batch import ConsistencyReport, Segment
from kf_train.estimator import (
    EstimatorSettings, NS_PER_S, Rejected, resolve_preset, StreamEstimator)
from kf_train.evaluate import later_fix, later_fix_errors
from kf_train.filters import MODE_NAMES, numba_available, STATE_NAMES
from kf_train.presets import RailPreset
from kf_train.ros import estimator_params
from kf_train.sim import RAIL_WARMUP_S
from kf_train.tune.inputs import TuneInput
import numpy as np

DEFAULT_HOLDOUT = 0.25
"""The fraction of each segment's time span held out (its end) by default."""
MIN_SPLIT_S = 120.0
"""A segment shorter than this is kept whole for the fit: its held-out part would hold
too few 2-s predictions (and the filter's warm-up) to judge anything."""

Window = Optional[Tuple[float, float]]
"""The times [start, end) [s] whose predictions are scored; None: none of the segment's."""
WORSE_TOLERANCE = 2e-3
"""RMSEs within this share (0.2 %, below the report's 3 digits) are a tie (the start kept)."""
GAIN_BLOCK_S = 10.0
"""The held-out gain is judged in blocks of this many seconds of predictions: 2-s
predictions made 0.2-0.4 s apart overlap, and a receiver's error is correlated over
seconds (docs/real-logs.md, D(τ)), so one prediction's gain is not independent of the
next's; blocks of 10 s nearly are."""
GAIN_SIGMAS = 2.0
"""A tuned setting is written only if its held-out gain exceeds this many standard errors."""
NIS_FACTOR = 10.0
"""A tuned model whose mean NIS is off by more than this factor (its 2σ band √10 ≈ 3.2×
too wide or too narrow), and further off than the start's, is refused: see
:func:`inconsistent_reason`."""


class Holdout(NamedTuple):
    """The tuning part and the held-out windows (one per segment)."""

    training: List[Segment]
    """Each segment's rows before its cut (whole when kept whole)."""
    windows: List[Window]
    """Each segment's held-out time window [cut, end], or None (kept whole)."""
    kept_whole: int
    """Segments shorter than MIN_SPLIT_S, kept whole for the fit."""


class SettingScore(NamedTuple):
    """A setting's 2-s predictions in the scored windows, and what the node did there."""

    rmse_m: float
    """RMSE against the later fix [m] (NaN: none scored)."""
    coverage: float
    """Share within 2σ (the prediction's variance plus the later fix's R in use, learned)."""
    count: int
    """Predictions scored against the later fix."""
    truth_rmse_m: Optional[float]
    """RMSE against the truth at t + 2 s [m]; None without truth."""
    resets: int
    """Resets (a lock-out with ``lockout: reset``, a clock jump, ...) in the windows."""
    reacquisitions: int
    """Lock-outs that kept the track, in the windows."""
    gated: int
    """Fixes the χ² gate rejected, in the windows."""
    mean_nis: float
    """Mean NIS of the fixes fused in the windows (NaN: none)."""
    errors_m: Optional[np.ndarray] = None
    """Each scored prediction's error against the later fix [m], the windows in order."""
    blocks: Optional[np.ndarray] = None
    """Each scored prediction's block (its segment, and GAIN_BLOCK_S of its window)."""


def split_holdout(segments: Sequence[Segment], fraction: float = DEFAULT_HOLDOUT) -> Holdout:
    """
    Return the first 1 − fraction of each segment's time span and the windows held out.

    The cut is at t₀ + (1 − fraction)·(t_end − t₀); rows before it are the training
    segment, predictions made from it on are scored. A segment shorter than
    MIN_SPLIT_S is kept whole for the fit (window None). ``fraction`` 0: no hold-out.
    """
    if not 0.0 <= fraction < 1.0:
        raise ValueError(f'the held-out fraction must be in [0, 1), got {fraction}')
    training, windows, whole = [], [], 0
    for s in segments:
        t = s.t_s
        span = float(t[-1] - t[0]) if t.size else 0.0
        if fraction == 0.0 or span < MIN_SPLIT_S:
            training.append(s)
            windows.append(None)
            whole += fraction > 0.0
            continue
        cut = float(t[0]) + (1.0 - fraction) * span
        rows = int(np.searchsorted(t, cut))
        training.append(Segment(*(None if a is None else a[:rows] for a in s)))
        windows.append((cut, math.inf))
    return Holdout(training, windows, whole)


def training_input(data: TuneInput, holdout: Holdout) -> TuneInput:
    """Return the input cut to the holdout's training part (its variances too)."""
    variances = data.measurement_variances
    if variances is not None:
        keep = np.concatenate([np.arange(s.t_s.shape[0]) < cut.t_s.shape[0]
                               for s, cut in zip(data.segments, holdout.training)])
        variances = variances[keep]
    return data._replace(segments=holdout.training, measurement_variances=variances)


def warm_windows(segments: Sequence[Segment]) -> List[Window]:
    """Return each segment's window after its warm-up (RAIL_WARMUP_S): scored whole."""
    return [(float(s.t_s[0]) + RAIL_WARMUP_S, math.inf) for s in segments]


def segment_variances(segments: Sequence[Segment], variances: Optional[np.ndarray]
                      ) -> Optional[List[np.ndarray]]:
    """Return the rows' position variances (TuneInput.measurement_variances) per segment."""
    if variances is None:
        return None
    ends = np.cumsum([s.t_s.shape[0] for s in segments])
    return np.split(np.asarray(variances, dtype=float)[:, 0], ends[:-1])


def node_settings(preset_path: str, measurement_variance: float = 0.0) -> EstimatorSettings:
    """Return the estimator node's default settings running a preset file."""
    settings = estimator_params.load_estimator_config().settings
    return dataclasses.replace(settings, preset=preset_path,
                               measurement_variance=float(measurement_variance))


def rail_preset_yaml(preset: RailPreset) -> str:
    """Return a rail preset as the YAML text of its file (loads back to the same preset)."""
    import yaml
    fields = dataclasses.asdict(preset.parameters)
    variance = fields.pop('noise_std_m') ** 2
    data = {'name': preset.name, 'description': preset.description, 'filter': 'imm',
            'model': 'rail_regimes', 'states': list(STATE_NAMES),
            'measurements': ['position'], 'modes': list(MODE_NAMES), 'R': [[variance]],
            'nominal_period_s': preset.nominal_period_s, 'parameters': fields}
    if preset.horizon_s is not None:
        data['horizon_s'] = preset.horizon_s
    return yaml.safe_dump(data, sort_keys=False, allow_unicode=True)


def _stamps_ns(t_s: np.ndarray) -> np.ndarray:
    """Return stamps [ns] > 0 keeping the steps: the times' own where they are positive."""
    origin_ns = round(float(t_s[0]) * NS_PER_S) if t_s[0] >= 1.0 else NS_PER_S
    return origin_ns + np.round((t_s - t_s[0]) * NS_PER_S).astype(np.int64)


class _Run(NamedTuple):
    """One segment through the estimator: the prediction made at each fix, the events."""

    mean: np.ndarray
    variance: np.ndarray
    r_m2: np.ndarray
    """The R each fix is weighed with once fused: the variance given times the learned scale."""
    nis: np.ndarray
    """NIS of each fused fix (NaN: not fused, or the first)."""
    gated: np.ndarray
    resets: int
    reacquisitions: int


def _run_segment(settings: EstimatorSettings, s: Segment, variances: np.ndarray,
                 window: Tuple[float, float], jit: bool) -> _Run:
    """Run one segment; keep each fix's 2-s prediction, count the events in ``window``."""
    estimator = StreamEstimator(settings, jit=jit)
    process, horizon_ns = estimator.process, round(estimator.horizon_s * NS_PER_S)
    N = s.t_s.shape[0]
    # Plain floats and lists: the loop runs ~100k times a tune, numpy scalars cost there.
    z, given = s.z[:, 0].tolist(), np.asarray(variances, dtype=float).tolist()
    mean, variance, nis = [math.nan] * N, [math.nan] * N, [math.nan] * N
    gated = [False] * N
    r_m2 = [estimator.measurement_variance(v) for v in given]   # as given, until learned
    in_use = estimator.variance_in_use
    # The stats at the window's edges: before its first fix and after its last (the times
    # increase, so its fixes are one run; without any, N: never reached, no events).
    in_window = np.flatnonzero((s.t_s >= window[0]) & (s.t_s < window[1])).tolist()
    first, last = (in_window[0], in_window[-1]) if in_window else (N, N)
    before = after = estimator.stats()
    for k, stamp_ns in enumerate(_stamps_ns(s.t_s).tolist()):
        if k == first:
            before = estimator.stats()
        try:
            step = process(stamp_ns, z[k], given[k])
        except Rejected as rejection:
            step, gated[k] = None, rejection.reason == 'outlier'
        if step is not None and step.prediction_stamp_ns - step.stamp_ns == horizon_ns:
            mean[k], variance[k] = step.predicted_x.item(0), step.predicted_P.item(0)
            if step.update is not None:
                nis[k] = step.update.nis
        elif estimator.initialized:        # rejected: the newest state, predicted on
            x, P = estimator.predict_to(stamp_ns + horizon_ns)
            mean[k], variance[k] = x.item(0), P.item(0)
        else:      # reset by this fix, not restarted yet: the fix held where it is
            mean[k], variance[k] = z[k], r_m2[k]
        if estimator.initialized:
            # The later fix's share of a band: what the filter now believes a fix adds
            # (the given R overstates a receiver's scatter up to 20-fold, so a band built
            # on it covers every error; docs/real-logs.md).
            r_m2[k] = in_use(given[k])
        if k == last:
            after = estimator.stats()
    return _Run(np.array(mean), np.array(variance), np.array(r_m2), np.array(nis),
                np.array(gated, dtype=bool),
                sum(after.resets.values()) - sum(before.resets.values()),
                after.reacquisitions - before.reacquisitions)


def _preset_path(preset: Union[RailPreset, str], directory: str) -> str:
    """Return a path the node's ``preset`` parameter takes: the file, or one written."""
    if isinstance(preset, str):
        return preset
    path = os.path.join(directory, 'preset.yaml')
    with open(path, 'w', encoding='utf-8') as stream:
        stream.write(rail_preset_yaml(preset))
    return path


def _runs(preset, segments, windows, variances, measurement_variance, settings, jit
          ) -> Iterator[Tuple[Segment, np.ndarray, _Run]]:
    """Yield (segment, rows scored, run) of every segment with a window."""
    with tempfile.TemporaryDirectory(prefix='kf-train-tune-') as directory:
        path = _preset_path(preset, directory)
        node = (node_settings(path, measurement_variance) if settings is None
                else dataclasses.replace(settings, preset=path,
                                         measurement_variance=float(measurement_variance)))
        default_r = float(resolve_preset(path).parameters.noise_std_m ** 2)
        for k, (s, window) in enumerate(zip(segments, windows)):
            if window is None or s.t_s.shape[0] == 0:
                continue
            rows = (variances[k] if variances is not None
                    else np.full(s.t_s.shape[0], default_r))
            run = _run_segment(node, s, rows, window, jit)
            yield s, (s.t_s >= window[0]) & (s.t_s < window[1]), run


def score_setting(preset: Union[RailPreset, str], segments: Sequence[Segment],
                  windows: Optional[Sequence[Window]] = None,
                  variances: Optional[Sequence[np.ndarray]] = None,
                  measurement_variance: float = 0.0,
                  settings: Optional[EstimatorSettings] = None,
                  jit: Optional[bool] = None) -> SettingScore:
    """
    Return the node's 2-s predictions in ``windows`` scored (see :class:`SettingScore`).

    ``preset``: a rail preset, or the path of its file (what the node's ``preset``
    parameter takes); ``windows``: one per segment (default: after the warm-up);
    ``variances``: each segment's rows' variances (a bag's), else the preset's R;
    ``measurement_variance``: the node's override (0: the rows'); ``settings``: the
    estimator's (default: the node's defaults; its preset and measurement_variance are
    these arguments'); ``jit``: the rail IMM compiled (None: where numba is installed;
    see the module docstring). The filter runs every segment from its first row; only
    predictions made in the window are scored.
    """
    windows = warm_windows(segments) if windows is None else windows
    jit = numba_available() if jit is None else jit
    fixes, truth, nis, errors, blocks = [], [], [], [], []
    gated = resets = reacquired = 0
    for k, (s, scored, run) in enumerate(_runs(preset, segments, windows, variances,
                                               measurement_variance, settings, jit)):
        against_fix = later_fix_errors(s.t_s, s.z[:, 0], run.mean, run.variance, run.r_m2,
                                       scored)
        fixes.append(against_fix.summary())
        errors.append(against_fix.error_m)
        t = s.t_s[against_fix.scored]
        blocks.append(k * 2 ** 32 + np.floor((t - t[:1]) / GAIN_BLOCK_S).astype(np.int64))
        if s.truth is not None:
            target, valid = later_fix(s.t_s, s.truth[:, 0])
            use = scored & valid & np.isfinite(target)
            truth.append((run.mean[use] - target[use]) ** 2)
        gated += int(run.gated[scored].sum())
        resets, reacquired = resets + run.resets, reacquired + run.reacquisitions
        nis.append(run.nis[scored & np.isfinite(run.nis)])
    fixes = [f for f in fixes if f.count]
    count = sum(f.count for f in fixes)
    # The windows pooled: each segment's figures weighted by its count.
    rmse = math.sqrt(sum(f.count * f.rmse_m ** 2 for f in fixes) / count) if count else math.nan
    coverage = sum(f.count * f.coverage for f in fixes) / count if count else math.nan
    truth = np.concatenate(truth) if truth else np.empty(0)
    nis = np.concatenate(nis) if nis else np.empty(0)
    return SettingScore(rmse, coverage, count,
                        float(np.sqrt(np.mean(truth))) if truth.size else None,
                        resets, reacquired, gated,
                        float(np.mean(nis)) if nis.size else math.nan,
                        np.concatenate(errors) if errors else np.empty(0),
                        np.concatenate(blocks) if blocks else np.empty(0, dtype=np.int64))


class Comparison(NamedTuple):
    """The start and the tuned setting scored on the same windows."""

    label: str
    """Where, for the report: e.g. 'held-out (last 25 %)', 'run2.mcap (after 10 s)'."""
    before: SettingScore
    after: SettingScore


def _m(value: Optional[float]) -> str:
    """Return a length [m] with 2 decimals ('-': none)."""
    return '-' if value is None or value != value else f'{value:.2f} m'


def comparison_lines(comparison: Comparison) -> List[str]:
    """Return the report's lines of a comparison (the truth's when there is truth)."""
    b, a = comparison.before, comparison.after
    if not b.count:
        return [f'{comparison.label}: no 2-s prediction with a later fix to score']
    lines = [f'{comparison.label}, {b.count} fixes: 2-s RMSE against the later fix before '
             f'{_m(b.rmse_m)}, after {_m(a.rmse_m)}; 2σ coverage {100 * b.coverage:.1f} % '
             f'-> {100 * a.coverage:.1f} %; resets {b.resets + b.reacquisitions} -> '
             f'{a.resets + a.reacquisitions}; gated {b.gated} -> {a.gated}; mean NIS '
             f'{b.mean_nis:.2f} -> {a.mean_nis:.2f}']
    if b.truth_rmse_m is not None and a.truth_rmse_m is not None:
        lines.append(f'{comparison.label}: 2-s RMSE against the truth before '
                     f'{_m(b.truth_rmse_m)}, after {_m(a.truth_rmse_m)}')
    return lines


def held_out_gain(before: SettingScore, after: SettingScore) -> Optional[Tuple[float, float]]:
    """
    Return (gain, its standard error) [m²]: Σ e_before² − e_after² over the same predictions.

    The gain is summed per block (GAIN_BLOCK_S of one segment's predictions); its
    standard error is √(blocks · the blocks' sample variance), the blocks taken as
    independent. None when the two were not scored on the same predictions or there
    are fewer than 2 blocks.
    """
    if (before.errors_m is None or after.errors_m is None
            or before.errors_m.shape != after.errors_m.shape
            or not np.array_equal(before.blocks, after.blocks)):
        return None
    _, block = np.unique(before.blocks, return_inverse=True)
    if block.size == 0 or block.max() < 1:
        return None
    sums = np.bincount(block, weights=before.errors_m ** 2 - after.errors_m ** 2)
    return float(sums.sum()), float(math.sqrt(sums.size * np.var(sums, ddof=1)))


def worse_reason(comparison: Comparison) -> Optional[str]:
    """
    Return why the tuned setting is worse than the start there, or None.

    Worse: a 2-s RMSE against the later fix, or against the truth where there is truth,
    larger by more than WORSE_TOLERANCE, or more lock-outs (resets and reacquisitions).
    A tie against the later fix (within WORSE_TOLERANCE) is refused too: without a gain
    there, the start is kept (a change that only might help is not worth the risk); so
    is a gain within GAIN_SIGMAS standard errors of the held-out part's own scatter
    (:func:`held_out_gain`): on tp-lib's logs the three tunes that made the next log
    worse had held-out gains of 0.5-1.1 standard errors (docs/rail.md).
    """
    b, a = comparison.before, comparison.after
    if not b.count:
        return None
    if a.rmse_m > b.rmse_m * (1.0 + WORSE_TOLERANCE):
        return (f'on {comparison.label} the tuned setting predicts worse (2-s RMSE '
                f'{_m(a.rmse_m)} against {_m(b.rmse_m)})')
    if a.rmse_m >= b.rmse_m * (1.0 - WORSE_TOLERANCE):
        return (f'on {comparison.label} the tuned setting predicts no better (2-s RMSE '
                f'{_m(a.rmse_m)} against {_m(b.rmse_m)}, within {100 * WORSE_TOLERANCE:g} %)')
    gain = held_out_gain(b, a)
    if gain is not None and not gain[0] > GAIN_SIGMAS * gain[1]:
        return (f'on {comparison.label} the tuned setting predicts better (2-s RMSE '
                f'{_m(a.rmse_m)} against {_m(b.rmse_m)}), but within the noise: a gain '
                f'of {gain[0]:.4g} m² in Σ error², under {GAIN_SIGMAS:g} standard errors '
                f'({GAIN_SIGMAS * gain[1]:.4g} m², from blocks of {GAIN_BLOCK_S:g} s)')
    if (b.truth_rmse_m is not None and a.truth_rmse_m is not None
            and a.truth_rmse_m > b.truth_rmse_m * (1.0 + WORSE_TOLERANCE)):
        return (f'on {comparison.label} the tuned setting predicts the truth worse (2-s '
                f'RMSE {_m(a.truth_rmse_m)} against {_m(b.truth_rmse_m)})')
    if a.resets + a.reacquisitions > b.resets + b.reacquisitions:
        return (f'on {comparison.label} the tuned setting locks out more often '
                f'({a.resets + a.reacquisitions} against {b.resets + b.reacquisitions})')
    return None


def inconsistent_reason(before: ConsistencyReport, after: ConsistencyReport) -> Optional[str]:
    """
    Return why the tuned model is refused for its own innovations, or None.

    Refused: its mean NIS is off 1 by more than NIS_FACTOR and further off than the
    start's (the tune made the model less consistent with the data it was fitted on).
    Such a fit has used the noises for something other than the innovations' size: on
    tp-lib's clean logs, whose receiver smooths its output, the likelihood raised q_ℓ
    500-1500× to follow the receiver's slow error as motion (mean NIS 0.27 -> 0.048 and
    0.15 -> 0.016), and on held-out parts of the same log that won; the tuned files then
    made dirty logs worse (docs/rail.md, "Real logs, tuned on one and judged on another").
    """
    def off(report):
        return abs(math.log(report.mean_nis)) if report.mean_nis > 0.0 else math.inf
    if off(after) <= math.log(NIS_FACTOR) or off(after) <= off(before):
        return None
    side = 'larger' if after.mean_nis < 1.0 else 'smaller'
    return (f'the tuned model is inconsistent with its own innovations (mean NIS '
            f'{after.mean_nis:.3g}, {before.mean_nis:.3g} before; off by more than '
            f'{NIS_FACTOR:g}×): its bands would be over {math.sqrt(NIS_FACTOR):.1f}× {side} '
            'than the errors; the noises were fitted to something other than the '
            "innovations' size (e.g. a smoothing receiver's slow error read as motion), "
            'and such noises made other logs worse')


def model_verdict(report: ConsistencyReport) -> List[str]:
    """
    Return plain sentences on what the innovations say is wrong with the model ([]: none).

    ``report``: :func:`kf_train.batch.nis_consistency` of the tuned filter's
    innovations: the mean NIS against its χ² bounds, the lag-1 autocorrelation
    against its bound.
    """
    sentences = []
    if report.lag1 > report.lag1_bound:
        sentences.append(
            f'the model does not describe this data: innovations are correlated '
            f'({report.lag1:.2f}, bound ±{report.lag1_bound:.2g}); the likely cause is a '
            'time-correlated measurement error (a receiver that filters its output, '
            'multipath that drifts), which no white measurement noise R can describe')
    elif report.lag1 < -report.lag1_bound:
        sentences.append(
            f'the model does not describe this data: innovations alternate in sign '
            f'({report.lag1:.2f}, bound ±{report.lag1_bound:.2g}); the likely cause is a '
            'filter that follows each fix too eagerly (process noise too large for the '
            'measurement noise), or fixes that jump back and forth')
    if report.mean_nis < report.low:
        sentences.append(
            f'the innovations are smaller than the filter expects (mean NIS '
            f'{report.mean_nis:.3g}, bounds [{report.low:.3g}, {report.high:.3g}]): the '
            'noise is set larger than the data show'
            + ('; with correlated innovations, part of the error is slow and the '
               'filter reads it as motion' if report.lag1 > report.lag1_bound else ''))
    elif report.mean_nis > report.high:
        sentences.append(
            f'the innovations are larger than the filter expects (mean NIS '
            f'{report.mean_nis:.3g}, bounds [{report.low:.3g}, {report.high:.3g}]): the '
            'noise is set smaller than the data show')
    return sentences

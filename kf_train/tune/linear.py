"""
The noise of a linear preset's filter, estimated from logged data: ``kf-train tune``'s work.

:func:`tune_linear` reads the input (:mod:`kf_train.tune.inputs`), finds the white-noise
acceleration density q and the measurement variance R by maximum likelihood of the
innovations (:mod:`kf_train.tune.noise_fit`), checks the filter before and after
(:func:`run_tuning`, :func:`format_report`) and writes the estimator's params file
(:func:`params_yaml`) and the tuned preset. The options are ``kf-train tune``'s
(:class:`TuneOptions`; the command line is :mod:`kf_train.cli.tune`). yaml is imported
when a file is written.
"""

import datetime
import math
import os
import time
from typing import List, NamedTuple, Optional, Sequence, Tuple

from kf_train.batch import (
    ConsistencyReport, is_constant_velocity, nis_consistency, NoiseParameterisation,
    NoiseSetting, prediction_errors, PredictionReport, STATE_UNITS, TuningProblem,
    VARIANCE_PARAMETERS)
from kf_train.io import check_output_path, write_atomic
from kf_train.presets import load_preset, load_preset_file, Preset, preset_from_mapping
from kf_train.tune.inputs import reader_for, TopicOptions, TuneInput
from kf_train.tune.noise_fit import estimate_noise, TuningResult
from kf_train.tune.validation import DEFAULT_HOLDOUT
import numpy as np

DEFAULT_HORIZON_S = 2.0
CHECK_CONFIDENCE = 0.99


class TuneOptions(NamedTuple):
    """``kf-train tune``'s options (:mod:`kf_train.cli.tune` documents each)."""

    input: str  # noqa: A003 (the option INPUT, as argparse names it)
    preset: Optional[str] = None
    config: Optional[str] = None
    output: str = '-'
    preset_output: Optional[str] = None
    fix_q: Optional[float] = None
    fix_r: Optional[List[float]] = None
    initial_state: bool = False
    initialization: Optional[str] = None
    first_velocity_std: float = 100.0
    t0: Optional[float] = None
    horizon: Optional[float] = None
    confidence: float = 0.95
    rail_noises: Optional[str] = None
    topic: Optional[str] = None
    control_topic: Optional[str] = None
    truth_topic: Optional[str] = None
    estimate_r: bool = False
    holdout: float = DEFAULT_HOLDOUT
    """Rail preset only: the fraction of each segment held out (0: none)."""
    validate: Optional[str] = None
    """Rail preset only: another input to score the start and the tuned setting on."""
    force: bool = False
    """Rail preset only: write the tuned setting even where it scores worse."""


def ros_parameters(preset_spec: str, preset: Preset, problem: TuningProblem,
                   setting: NoiseSetting, r_given: bool) -> dict:
    """Return the estimator node's parameters for ``setting`` (insertion-ordered)."""
    params = {'preset': preset_spec,
              'process_noise_density': float(setting.process_noise_density)}
    if r_given and setting.measurement_variances is not None:
        for name, variance in zip(preset.measurement_names, setting.measurement_variances):
            if name in VARIANCE_PARAMETERS:
                params[VARIANCE_PARAMETERS[name]] = float(variance)
    params['initialization'] = problem.initialization
    if problem.initialization == 'first_measurement':
        params['first_velocity_std_mps'] = problem.first_velocity_std_mps
    elif setting.initial_state is not None:
        params['initial_state'] = [float(v) for v in setting.initial_state]
    return params


def params_yaml(params: dict, comments: Sequence[str]) -> str:
    """Return a ROS 2 params file for the ``estimator`` node, with leading comments."""
    import yaml
    body = yaml.safe_dump({'estimator': {'ros__parameters': params}}, sort_keys=False,
                          allow_unicode=True, default_flow_style=False)
    return ''.join(f'# {line}\n' for line in comments) + body


def tuned_preset_yaml(preset: Preset, setting: NoiseSetting) -> str:
    """Return the preset file of ``preset`` with the tuned noise, for replay --config."""
    import yaml
    with open(preset.source, encoding='utf-8') as stream:
        data = yaml.safe_load(stream)
    q = setting.process_noise_density
    if q > 0.0:
        noise = dict(data['process_noise'])
        continuous = np.zeros((preset.dim_x, preset.dim_x))
        if preset.dynamics.continuous is not None:
            continuous += preset.dynamics.continuous
        continuous[1, 1] += q        # white-noise acceleration: Qc = diag(0, q)
        noise['continuous'] = continuous.tolist()
        data['process_noise'] = noise
    if setting.measurement_variances is not None:
        data['R'] = np.diag(setting.measurement_variances).tolist()
    if setting.initial_state is not None:
        data['initial_state'] = [float(v) for v in setting.initial_state]
    data['name'] = f"{data['name']}-tuned"
    data['description'] = f"{data.get('description', '')} (noise tuned by kf-train tune)"
    preset_from_mapping(data, source='tuned preset')   # must load back
    return yaml.safe_dump(data, sort_keys=False, allow_unicode=True)


# ---------------------------------------------------------------------------
# Tuning and the report
# ---------------------------------------------------------------------------

class TuneReport(NamedTuple):
    """Everything ``kf-train tune`` prints."""

    result: TuningResult
    before: NoiseSetting
    before_log_likelihood: float
    nis_before: ConsistencyReport
    nis_after: ConsistencyReport
    prediction_before: Optional[PredictionReport]
    prediction_after: Optional[PredictionReport]
    seconds: float


def run_tuning(problem: TuningProblem, parameterisation: NoiseParameterisation,
               horizon_s: float, confidence: float,
               before: NoiseSetting = NoiseSetting()) -> TuneReport:
    """Estimate, then check the untuned noise (``before``) against the estimate (after)."""
    start = time.perf_counter()
    result = estimate_noise(problem, parameterisation, confidence=confidence)
    seconds = time.perf_counter() - start
    after = result.setting
    return TuneReport(
        result, before, problem.log_likelihood(before),
        nis_consistency(problem.innovations(before), CHECK_CONFIDENCE),
        nis_consistency(problem.innovations(after), CHECK_CONFIDENCE),
        prediction_errors(problem, before, horizon_s),
        prediction_errors(problem, after, horizon_s), seconds)


def _number(value: float) -> str:
    """Return a number with 4 significant digits."""
    return 'inf' if math.isinf(value) else f'{value:.4g}'


def _nis_line(report: ConsistencyReport) -> str:
    """Return one setting's NIS figures."""
    return f'{_number(report.mean_nis)} ({report.verdict})'


def format_report(report: TuneReport, problem: TuningProblem, confidence: float) -> str:
    """Return the printed report."""
    result = report.result
    segments = len(problem.segments)
    lines = [f'kf-train tune: preset {problem.preset.name}, '
             f'{sum(len(s.t_s) for s in problem.segments)} rows '
             f'({segments} object{"s" * (segments != 1)}), {result.rows} innovations, '
             f'initialization {problem.initialization}',
             f'maximum likelihood: {result.evaluations} likelihood evaluations, '
             f'{report.seconds:.2f} s' + ('' if result.converged else
                                          f' (optimiser: {result.message})'),
             f'  {"parameter":<50} {"estimate":>10}  {f"{confidence:.0%} interval":<24}'
             f'{"std. error":>10}']
    for e in result.estimates:
        label = f'{e.parameter.symbol:<12} {e.parameter.name}'
        label += f' [{e.parameter.unit}]' if e.parameter.unit else ''
        interval = (f'[{_number(e.low)}, {_number(e.high)}]' if e.method != 'unidentified'
                    else 'not identified')
        note = '  (compatible with 0: profile bound)' if e.method == 'profile' else ''
        lines.append(f'  {label:<50} {_number(e.value):>10}  {interval:<24}'
                     f'{_number(e.std_error) if e.std_error == e.std_error else "-":>10}{note}')
    b, a = report.nis_before, report.nis_after
    lines += [f'log-likelihood: before {report.before_log_likelihood:.2f}, after '
              f'{result.log_likelihood:.2f}',
              f'NIS, mean of {a.count} χ²({a.dof}) ({CHECK_CONFIDENCE:.0%} bounds '
              f'[{a.low:.4g}, {a.high:.4g}]): before {_nis_line(b)}, after {_nis_line(a)}',
              f'lag-1 autocorrelation of the innovations ({CHECK_CONFIDENCE:.0%} bound '
              f'±{a.lag1_bound:.3g}): before {b.lag1:.3g} '
              f'({"white" if b.white else "not white"}), after {a.lag1:.3g} '
              f'({"white" if a.white else "not white"})']
    if a.verdict == 'noise too large':
        lines.append("note: even the tuned filter's noise is too large for the data: the "
                     "preset's own process noise is (tune only adds q); lower its "
                     'process_noise in a preset file')
    elif a.verdict == 'noise too small' or not a.white:
        lines.append('note: the tuned filter still does not fit the data (outliers, a bias, '
                     'manoeuvres unlike white noise, or noise that changes during the run)')
    pb, pa = report.prediction_before, report.prediction_after
    if pa is None:
        lines.append('prediction RMSE: no truth columns (true_<state>) in the input')
    else:
        unit = {name: ' ' + STATE_UNITS[name] if name in STATE_UNITS else '' for name in pa.rmse}
        parts = [f'{name} before {_number(pb.rmse[name])}{unit[name]}, after '
                 f'{_number(pa.rmse[name])}{unit[name]}' for name in pa.rmse]
        lines.append(f'{pa.horizon_s:g}-s prediction RMSE ({pa.count} rows with truth): '
                     + '; '.join(parts))
    return '\n'.join(lines)


def carried_variances(data: TuneInput, estimate_r: bool
                      ) -> Tuple[Optional[Tuple[float, ...]], Optional[str]]:
    """
    Return (R the data carry, a note): R when every row carries the same variances.

    None when the data carry none (a table), when ``estimate_r``, or when they vary
    (then the note says one R is estimated instead).
    """
    variances = data.measurement_variances
    if variances is None:
        return None, None
    low, high = np.min(variances, axis=0), np.max(variances, axis=0)
    carried = ', '.join(f'{a:.4g}' if a == b else f'{a:.4g} to {b:.4g}'
                        for a, b in zip(low.tolist(), high.tolist()))
    if estimate_r:
        return None, f'the messages carry the variance(s) {carried}; --estimate-r: R estimated'
    if np.array_equal(low, high) and np.all(low > 0.0) and np.all(np.isfinite(low)):
        return tuple(low.tolist()), (f'R = {carried}, as the messages carry it (the node '
                                     'uses it); --estimate-r estimates it instead')
    return None, (f'the messages carry varying variances ({carried}): one R is estimated, '
                  'which measurement_variance makes the node use instead')


def _setup(args: TuneOptions):
    """Return (preset spec, preset, problem, parameterisation, input, notes)."""
    spec = os.path.abspath(args.config) if args.config else (args.preset or 'train')
    preset = load_preset_file(args.config) if args.config else load_preset(spec)
    topics = TopicOptions(args.topic, args.control_topic, args.truth_topic)
    data = reader_for(args.input)(args.input, preset, topics)
    segments = data.segments
    carried, note = carried_variances(data, args.estimate_r)
    notes = [line for line in (data.summary, note) if line]
    initialization = args.initialization or ('prior' if args.initial_state
                                             else 'first_measurement')
    problem = TuningProblem(preset, segments, initialization=initialization,
                            first_velocity_std_mps=args.first_velocity_std,
                            prior_t0_s=args.t0 if initialization == 'prior' else None)
    if args.fix_r is not None and len(args.fix_r) != preset.dim_z:
        raise ValueError(f'--fix-r needs {preset.dim_z} variance(s), one per measurement '
                         f'({", ".join(preset.measurement_names)}), got {len(args.fix_r)}')
    fixed_r = tuple(args.fix_r) if args.fix_r is not None else carried
    fixed = NoiseSetting(args.fix_q or 0.0, fixed_r)
    estimate_q = args.fix_q is None and is_constant_velocity(preset)
    parameterisation = NoiseParameterisation(
        problem, process_noise=estimate_q, measurement_noise=fixed_r is None,
        initial_state=args.initial_state, fixed=fixed)
    # Before: what the node runs untuned, the messages' variance where constant.
    before = NoiseSetting(0.0, carried if not args.estimate_r else
                          carried_variances(data, False)[0])
    return spec, preset, problem, parameterisation, before, notes


def tune_linear(args: TuneOptions) -> str:
    """Tune a linear preset on ``args.input``, write the files; return the report."""
    for target in (args.output, args.preset_output):
        if target not in (None, '-'):
            check_output_path(target)       # before the work, not after
    spec, preset, problem, parameterisation, before, notes = _setup(args)
    horizon_s = args.horizon or preset.horizon_s or DEFAULT_HORIZON_S
    report = run_tuning(problem, parameterisation, horizon_s, args.confidence, before)
    setting = report.result.setting
    # R the messages carry stays theirs (measurement_variance 0: the message's).
    r_given = args.fix_r is not None or bool(parameterisation.measured)
    params = ros_parameters(spec, preset, problem, setting, r_given)
    comments = [f'Written by kf-train tune on {datetime.date.today().isoformat()} from '
                f'{args.input} ({report.result.rows} innovations), preset {preset.name}.']
    comments += [f'{e.parameter.name} = {_number(e.value)}, {args.confidence:.0%} '
                 f'interval [{_number(e.low)}, {_number(e.high)}]'
                 for e in report.result.estimates]
    comments += [f'input: {line}' for line in notes]
    comments.append(f'Use: estimator --ros-args --params-file {os.path.basename(args.output)}'
                    f' (or kf-train replay BAG --params-file {os.path.basename(args.output)})')
    head, _, rest = format_report(report, problem, args.confidence).partition('\n')
    text = '\n'.join([head] + [f'input: {line}' for line in notes] + [rest])
    if args.preset_output:
        write_atomic(args.preset_output, [tuned_preset_yaml(preset, setting)])
    write_atomic(args.output, [params_yaml(params, comments)])
    return text + f'\nwrote {args.output}' + (
        f' and {args.preset_output}' if args.preset_output else '')

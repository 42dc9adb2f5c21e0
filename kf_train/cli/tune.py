"""
``kf-train tune``: the noise of a preset's filter, estimated from logged measurements.

    kf-train tune [--preset P | --config FILE] INPUT --output PARAMS.yaml

The default preset is the estimator node's, ``rail`` (its IMM's noises are tuned by
:mod:`kf_train.cli.tune_rail`); for the linear presets (``--preset train`` ...):

It finds the white-noise acceleration density q (``process_noise_density``) and the
measurement variance R (``measurement_variance``; ``measurement_velocity_variance``
too for cv-position-velocity) that make the data most likely under the estimator
node's own filter (:class:`kf_train.batch.TuningProblem`: exact likelihood of the
innovations, maximised with scipy by :mod:`kf_train.cli.noise_fit`), and prints:

* the estimates with their confidence intervals (curvature of the log-likelihood;
  a q the data cannot tell from 0 gets [0, its profile-likelihood bound]);
* the NIS consistency before (the preset's own noise) and after, against the two-sided
  99 % χ² bounds of the mean NIS, and the innovations' lag-1 whiteness;
* where the input has the truth (columns ``true_position``, ``true_velocity``), the
  RMSE of the prediction ``--horizon`` ahead (the preset's, else 2 s) before and after.

It writes PARAMS.yaml, ``estimator: ros__parameters:`` with the preset and the tuned
values, for ``estimator --ros-args --params-file PARAMS.yaml`` and for ``kf-train
replay BAG --params-file PARAMS.yaml``; ``--preset-output FILE`` also writes the tuned
preset, for ``kf-train replay TABLE --config FILE``.

Input: what ``kf-train replay`` reads (:mod:`kf_train.cli.tune_inputs`): a CSV
(``t``, the measurement columns, ``u`` where the preset has a control, optionally
``id``: every id is an object of its own, all sharing the noise), Parquet with the
same columns, plus optional truth columns ``true_<state>``; or a rosbag2 bag (a
directory, ``.mcap`` or ``.db3``), its topics chosen as ``kf-train replay BAG`` chooses
them (``--topic``, ``--control-topic``), truth from ``--truth-topic`` (default
``ground_truth`` when there). A table does not carry the measurements' variance, so R
is estimated unless ``--fix-r`` gives it. A bag does: when every message carries the
same variance, that is R (the node uses the message's variance) and q alone is
estimated, unless ``--estimate-r``; when the variances vary, one R is estimated.
Bad input is reported in one line (file, line or row, column; the bag and its topic)
with exit code 1.
"""

import argparse
import datetime
import math
import os
import sys
import time
from typing import List, NamedTuple, Optional, Sequence, Tuple

from kf_train.batch import (
    ConsistencyReport, is_constant_velocity, nis_consistency, NoiseParameterisation,
    NoiseSetting, prediction_errors, PredictionReport, STATE_UNITS, TuningProblem,
    VARIANCE_PARAMETERS)
from kf_train.cli.noise_fit import estimate_noise, TuningResult
from kf_train.cli.tune_inputs import read_bag, reader_for, TopicOptions, TuneInput
from kf_train.cli.tune_rail import add_rail_arguments, check_rail_args, rail_preset_of, tune_rail
from kf_train.io import check_output_path, write_atomic
from kf_train.presets import (
    available_presets, load_preset, load_preset_file, Preset, preset_from_mapping)
import numpy as np

EXIT_OK = 0
EXIT_BAD_INPUT = 1
EXIT_USAGE = 2
DEFAULT_HORIZON_S = 2.0
CHECK_CONFIDENCE = 0.99


# ---------------------------------------------------------------------------
# Outputs
# ---------------------------------------------------------------------------

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


# ---------------------------------------------------------------------------
# Command line
# ---------------------------------------------------------------------------

def _parser() -> argparse.ArgumentParser:
    """Return the argument parser."""
    parser = argparse.ArgumentParser(
        prog='kf-train tune',
        description="Estimate the estimator's noise from logged measurements (maximum "
                    "likelihood of the filter's innovations: the rail IMM's acceleration "
                    'and command noises by default, q for the linear presets; R where the '
                    'data do not carry it) and write them as a ROS params file.',
        epilog='Input: what kf-train replay reads: a CSV or Parquet (t, z_<measurement>, '
               'u, optional id, optional truth columns true_<state> for the prediction '
               'RMSE), or a rosbag2 bag (a directory, .mcap or .db3: the '
               'node measurement and control topics, truth from an Odometry topic). '
               'Needs scipy (pip install scipy).')
    parser.add_argument('input', metavar='INPUT',
                        help="the measurements: CSV ('-': stdin), a .parquet file or a "
                             'directory of them, or a rosbag2 bag (a directory, .mcap or .db3)')
    source = parser.add_mutually_exclusive_group()
    source.add_argument('--preset', metavar='NAME', choices=['rail'] + available_presets(),
                        default=None, help="a shipped preset (default rail, the node's): "
                                           '%(choices)s')
    source.add_argument('--config', metavar='FILE', help='a preset YAML file of your own')
    parser.add_argument('--output', '-o', metavar='PARAMS.yaml', required=True,
                        help='where to write the estimator params file')
    parser.add_argument('--preset-output', metavar='FILE',
                        help='also write the tuned preset, for kf-train replay --config')
    parser.add_argument('--fix-q', metavar='Q', type=float,
                        help='do not estimate q: use this density [m²/s³]')
    parser.add_argument('--fix-r', metavar='R', type=float, nargs='+',
                        help='do not estimate R: the measurement variance(s), one per '
                             'measurement (what the messages carry)')
    parser.add_argument('--initial-state', action='store_true',
                        help='also estimate the initial state (uses the prior '
                             'initialization)')
    parser.add_argument('--initialization', choices=('first_measurement', 'prior'),
                        help="the node's initialization (default first_measurement; prior "
                             'with --initial-state)')
    parser.add_argument('--first-velocity-std', metavar='MPS', type=float, default=100.0,
                        help='first_measurement: σ of the initial velocity [m/s] (100)')
    parser.add_argument('--t0', metavar='S', type=float,
                        help='prior: the time of the initial estimate [s] (default: one '
                             'nominal period before the first row of each object, as the node)')
    parser.add_argument('--horizon', metavar='S', type=float,
                        help="prediction horizon of the RMSE [s] (default: the preset's, "
                             'else 2)')
    parser.add_argument('--confidence', metavar='P', type=float, default=0.95,
                        help='confidence of the intervals (0.95)')
    add_rail_arguments(parser)
    bag = parser.add_argument_group('bag input (a rosbag2 directory, .mcap or .db3)')
    bag.add_argument('--topic', metavar='NAME', default=None,
                     help="the measurement topic (default: 'measurement' resolved in the "
                          'bag, else the only one of the expected type), as kf-train replay')
    bag.add_argument('--control-topic', metavar='NAME', default=None,
                     help="the control topic, for presets with one (default: 'control')")
    bag.add_argument('--truth-topic', metavar='NAME', default=None,
                     help='an Odometry topic with the true state, for the prediction RMSE '
                          "(default: 'ground_truth' if the bag has it)")
    bag.add_argument('--estimate-r', action='store_true',
                     help='estimate R even though the messages carry a variance (the '
                          "sensor's stated covariance is a guess)")
    return parser


def _check_args(parser: argparse.ArgumentParser, args) -> None:
    """Refuse out-of-range options (exit 2)."""
    for option, value, low in (('--fix-q', args.fix_q, 0.0), ('--horizon', args.horizon, 0.0),
                               ('--first-velocity-std', args.first_velocity_std, 0.0)):
        if value is not None and not (math.isfinite(value) and value >= low):
            parser.error(f'{option} must be a finite number >= {low:g}, got {value}')
    for value in args.fix_r or ():
        if not (math.isfinite(value) and value > 0.0):
            parser.error(f'--fix-r must be finite numbers > 0, got {value}')
    if not 0.5 <= args.confidence < 1.0:
        parser.error(f'--confidence must be in [0.5, 1), got {args.confidence}')
    if args.t0 is not None and not math.isfinite(args.t0):
        parser.error(f'--t0 must be a finite number, got {args.t0}')
    if args.initial_state and args.initialization == 'first_measurement':
        parser.error('--initial-state needs --initialization prior')
    if args.estimate_r and args.fix_r is not None:
        parser.error('--estimate-r and --fix-r exclude each other')
    if reader_for(args.input) is not read_bag:
        for option in ('topic', 'control_topic', 'truth_topic'):
            if getattr(args, option) is not None:
                parser.error(f"--{option.replace('_', '-')} applies to a bag input only")


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


def _setup(args):
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


def _tune_linear(args) -> str:
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


def main(argv: Optional[List[str]] = None) -> int:
    """Run ``kf-train tune``; return the exit code."""
    parser = _parser()
    args = parser.parse_args(sys.argv[1:] if argv is None else argv)
    _check_args(parser, args)
    try:
        rail = rail_preset_of(args)
        if rail is not None:
            noises = check_rail_args(parser, args)
            text = tune_rail(args, rail, noises, os.path.abspath(args.config) if args.config
                             else 'rail')
        elif args.rail_noises is not None:
            parser.error('--rail-noises applies to the rail preset only')
        else:
            text = _tune_linear(args)
    except ImportError as error:
        print(f'kf-train tune: error: needs scipy ({error}); install it with '
              "'pip install scipy'", file=sys.stderr)
        return EXIT_BAD_INPUT
    except ValueError as error:
        print(f'kf-train tune: error: {" ".join(str(error).split())}', file=sys.stderr)
        return EXIT_BAD_INPUT
    print(text, file=sys.stderr if args.output == '-' else sys.stdout)
    return EXIT_OK


if __name__ == '__main__':
    sys.exit(main())

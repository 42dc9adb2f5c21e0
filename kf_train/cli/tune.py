"""
``kf-train tune``: the noise of a preset's filter, estimated from logged measurements.

    kf-train tune [--preset P | --config FILE] INPUT --output PARAMS.yaml

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
values, for ``estimator --ros-args --params-file PARAMS.yaml``. ``kf-train replay``
takes no params file (its ``--config`` is a preset file): ``--preset-output FILE``
also writes the tuned preset for ``kf-train replay --config FILE``.

Input: the CSV of ``kf-train replay`` (``t``, the measurement columns, ``u`` where the
preset has a control, optionally ``id``: every id is an object of its own, all
sharing the noise), plus optional truth columns ``true_<state>``. Readers are
chosen by :func:`reader_for`; a rosbag2 reader plugs in there when bag reading exists.
R is estimated (a CSV does not carry the measurements' variance) unless ``--fix-r``
gives it. Bad input is reported in one line (file, line, column) with exit code 1.
"""

import argparse
import datetime
import math
import os
import sys
import time
from typing import Callable, List, NamedTuple, Optional, Sequence

from kf_train.batch import (
    ConsistencyReport, group_rows, is_constant_velocity, nis_consistency, NoiseParameterisation,
    NoiseSetting, prediction_errors, PredictionReport, Segment, STATE_UNITS, TuningProblem,
    VARIANCE_PARAMETERS)
from kf_train.cli.noise_fit import estimate_noise, TuningResult
from kf_train.cli.replay import (
    check_bank_times, check_times, InputError, read_table, required_columns, write_atomic)
from kf_train.presets import (
    available_presets, load_preset, load_preset_file, Preset, preset_from_mapping)
import numpy as np

EXIT_OK = 0
EXIT_BAD_INPUT = 1
EXIT_USAGE = 2
DEFAULT_HORIZON_S = 2.0
CHECK_CONFIDENCE = 0.99
TRUTH_PREFIX = 'true_'
BAG_SUFFIXES = ('.mcap', '.db3')


# ---------------------------------------------------------------------------
# Input readers: path -> segments
# ---------------------------------------------------------------------------

def _read_bytes(path: str) -> bytes:
    """Return the input's bytes ('-': standard input)."""
    if path == '-':
        return sys.stdin.buffer.read() if hasattr(sys.stdin, 'buffer') else \
            sys.stdin.read().encode('utf-8')
    try:
        with open(path, 'rb') as stream:
            return stream.read()
    except OSError as error:
        raise InputError(f'{path}: cannot read: {error.strerror}') from None


def _header(data: bytes) -> List[str]:
    """Return the header's column names (the table reader checks it properly)."""
    line = data.split(b'\n', 1)[0].lstrip(b'\xef\xbb\xbf').decode('utf-8', 'replace')
    return [name.strip().strip('"').strip() for name in line.split(',')]


def read_csv(path: str, preset: Preset) -> List[Segment]:
    """Return the segments of a replay CSV (one per id), with truth where given."""
    data = _read_bytes(path)
    header = _header(data)
    truth_columns = [TRUTH_PREFIX + s for s in preset.state_names if TRUTH_PREFIX + s in header]
    table = read_table(path, required_columns(preset) + [(c,) for c in truth_columns], data,
                       ids=True)
    if table.rows == 0:
        raise InputError(f'{path}: no rows: nothing to estimate from')
    t = table.columns['t']
    first = float(np.min(t))
    if table.ids is None:
        check_times(path, t, table.lines, first)
        groups = group_rows(np.zeros(table.rows, dtype=np.int64))
    else:
        groups = group_rows(table.ids)
        check_bank_times(path, t, table.lines, groups, table.id_labels, first)
    z = np.column_stack([table.columns[next(n for n in names if n in table.columns)]
                         for names in preset.measurement_columns()])
    u = (np.column_stack([table.columns[n] for n in preset.control_columns()])
         if preset.dim_u else None)
    truth = None
    if truth_columns:
        truth = np.full((table.rows, preset.dim_x), np.nan)
        for i, state in enumerate(preset.state_names):
            if TRUTH_PREFIX + state in table.columns:
                truth[:, i] = table.columns[TRUTH_PREFIX + state]
    segments = []
    for k in range(groups.counts.shape[0]):
        rows = groups.rows(k)
        segments.append(Segment(t[rows], z[rows], None if u is None else u[rows],
                                None if truth is None else truth[rows]))
    return segments


InputReader = Callable[[str, Preset], List[Segment]]


def reader_for(path: str) -> InputReader:
    """Return the reader of an input path; a bag (directory, .mcap, .db3) is refused."""
    if path != '-' and (os.path.isdir(path) or path.lower().endswith(BAG_SUFFIXES)):
        raise InputError(f'{path}: bag input is not supported yet; export the measurements '
                         'to a CSV (t, z_position, ...) and tune that')
    return read_csv


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
               horizon_s: float, confidence: float) -> TuneReport:
    """Estimate, then check the preset's own noise (before) against the estimate (after)."""
    start = time.perf_counter()
    result = estimate_noise(problem, parameterisation, confidence=confidence)
    seconds = time.perf_counter() - start
    before = NoiseSetting()
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
        description="Estimate the estimator's process noise density q and measurement "
                    'variance R from logged measurements (maximum likelihood of the '
                    "filter's innovations) and write them as a ROS params file.",
        epilog='Input: the CSV of kf-train replay (t, z_<measurement>, u, optional id) '
               'with optional truth columns true_<state> for the prediction RMSE. '
               'Needs scipy (pip install scipy).')
    parser.add_argument('input', metavar='INPUT', help="the measurements ('-': stdin)")
    source = parser.add_mutually_exclusive_group()
    source.add_argument('--preset', metavar='NAME', choices=available_presets(),
                        default=None, help='a shipped preset (default train): %(choices)s')
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


def _setup(args):
    """Return (preset spec, preset, problem, parameterisation) from the arguments."""
    spec = os.path.abspath(args.config) if args.config else (args.preset or 'train')
    preset = load_preset_file(args.config) if args.config else load_preset(spec)
    segments = reader_for(args.input)(args.input, preset)
    initialization = args.initialization or ('prior' if args.initial_state
                                             else 'first_measurement')
    problem = TuningProblem(preset, segments, initialization=initialization,
                            first_velocity_std_mps=args.first_velocity_std,
                            prior_t0_s=args.t0 if initialization == 'prior' else None)
    if args.fix_r is not None and len(args.fix_r) != preset.dim_z:
        raise ValueError(f'--fix-r needs {preset.dim_z} variance(s), one per measurement '
                         f'({", ".join(preset.measurement_names)}), got {len(args.fix_r)}')
    fixed = NoiseSetting(args.fix_q or 0.0, None if args.fix_r is None else tuple(args.fix_r))
    estimate_q = args.fix_q is None and is_constant_velocity(preset)
    parameterisation = NoiseParameterisation(
        problem, process_noise=estimate_q, measurement_noise=args.fix_r is None,
        initial_state=args.initial_state, fixed=fixed)
    return spec, preset, problem, parameterisation


def main(argv: Optional[List[str]] = None) -> int:
    """Run ``kf-train tune``; return the exit code."""
    parser = _parser()
    args = parser.parse_args(sys.argv[1:] if argv is None else argv)
    _check_args(parser, args)
    try:
        spec, preset, problem, parameterisation = _setup(args)
        horizon_s = args.horizon or preset.horizon_s or DEFAULT_HORIZON_S
        report = run_tuning(problem, parameterisation, horizon_s, args.confidence)
        setting = report.result.setting
        r_given = args.fix_r is not None or bool(parameterisation.measured)
        params = ros_parameters(spec, preset, problem, setting, r_given)
        comments = [f'Written by kf-train tune on {datetime.date.today().isoformat()} from '
                    f'{args.input} ({report.result.rows} innovations), preset {preset.name}.']
        comments += [f'{e.parameter.name} = {_number(e.value)}, {args.confidence:.0%} '
                     f'interval [{_number(e.low)}, {_number(e.high)}]'
                     for e in report.result.estimates]
        comments.append(f'Use: estimator --ros-args --params-file {os.path.basename(args.output)}')
        text = format_report(report, problem, args.confidence)
        if args.preset_output:
            write_atomic(args.preset_output, [tuned_preset_yaml(preset, setting)])
        write_atomic(args.output, [params_yaml(params, comments)])
    except ImportError as error:
        print(f'kf-train tune: error: needs scipy ({error}); install it with '
              "'pip install scipy'", file=sys.stderr)
        return EXIT_BAD_INPUT
    except ValueError as error:
        print(f'kf-train tune: error: {" ".join(str(error).split())}', file=sys.stderr)
        return EXIT_BAD_INPUT
    stream = sys.stderr if args.output == '-' else sys.stdout
    print(text, file=stream)
    print(f'wrote {args.output}' + (f' and {args.preset_output}' if args.preset_output
                                    else ''), file=stream)
    return EXIT_OK


if __name__ == '__main__':
    sys.exit(main())

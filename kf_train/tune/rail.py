"""
``kf-train tune --preset rail``: the rail IMM's noises, estimated from logged measurements.

The rail preset (docs/rail.md) has no white-noise acceleration density q: each moving
regime has an acceleration noise q_a and a command noise q_ℓ (``acceleration_noise``,
``command_noise``), and the measurement variance R. This module estimates those the
data can identify by maximum likelihood of the innovations of the filter the node runs
(:mod:`kf_train.batch.rail_likelihood`: the rows' variances, the learned scale on R, the
χ² gate; maximised by :mod:`kf_train.tune.rail_fit`), checks the node's innovations
before and after (NIS, whiteness, a verdict in words), scores the node untuned and tuned
on the held-out end of the input (and ``--validate``'s: :mod:`kf_train.tune.validation`),
and, unless the tuned setting predicts worse there, writes

* a tuned rail preset file (``--preset-output``, by default next to PARAMS.yaml as
  ``<name>-rail.yaml``): the preset with the tuned noises, which the node reads through
  its ``preset`` parameter (a YAML path with ``model: rail_regimes``), and
  ``kf-train replay TABLE --config`` too;
* PARAMS.yaml, ``estimator: ros__parameters:`` with ``preset`` the absolute path of that
  file and ``measurement_variance`` where R was estimated or given.

The inputs and their options are ``kf-train tune``'s (:class:`kf_train.tune.TuneOptions`;
the command line is :mod:`kf_train.cli.tune`).
"""

import datetime
import math
import os
from typing import List, Optional, Tuple

from kf_train.batch import Innovations, nis_consistency, rail_log_likelihoods, RailNoise
from kf_train.filters import chi2_quantile
from kf_train.io import check_output_path, write_atomic
from kf_train.presets import (
    is_rail_preset_file, load_rail_preset, rail_preset_from_mapping, RAIL_PRESET_NAME,
    RailPreset)
from kf_train.sim import RAIL_WARMUP_S
from kf_train.tune.inputs import reader_for, TopicOptions, TuneInput
from kf_train.tune.linear import carried_variances, params_yaml, TuneOptions
from kf_train.tune.rail_fit import fit_rail_noise, MIN_GAIN, RailFit
from kf_train.tune.validation import (
    Comparison, comparison_lines, Holdout, inconsistent_reason, MIN_SPLIT_S, model_verdict,
    node_settings, score_setting, segment_variances, split_holdout, training_input,
    warm_windows, worse_reason)
import numpy as np

CHECK_CONFIDENCE = 0.99
DEFAULT_NOISES = ('acceleration_noise', 'command_noise')
TUNABLE_NOISES = ('acceleration_noise', 'command_noise', 'capability_noise')


def _moment_variance(segments) -> float:
    """
    Return R from the second differences of the measurements (a start, not an estimate).

    d_k = z_{k+1} − 2 z_k + z_{k−1} is 4R + 2R = 6R in variance with lag-1 covariance
    −4R when the motion's own second difference (a·dt², ~0.01 m at 10 Hz) is
    negligible: R = (γ₀ − 4γ₁)/22 as for the linear presets.
    """
    g0 = g1 = 0.0
    count = 0
    for s in segments:
        if s.z.shape[0] < 4:
            continue
        d = np.diff(s.z[:, 0], n=2)
        g0 += float(np.sum(d * d))
        g1 += float(np.sum(d[1:] * d[:-1]))
        count += d.shape[0]
    if count < 2 or g0 <= 0.0:
        raise ValueError('the measurements do not vary (or there are fewer than 4 rows per '
                         'object): nothing to estimate the noise from')
    g0, g1 = g0 / count, g1 / (count - 1)
    return max((g0 - 4.0 * g1) / 22.0, g0 / 600.0)


def tuned_rail_yaml(preset: RailPreset, setting: RailNoise) -> str:
    """Return the rail preset file with the tuned noises (checked to load back)."""
    import yaml
    with open(preset.source, encoding='utf-8') as stream:
        data = yaml.safe_load(stream)
    parameters = dict(data.get('parameters') or {})
    for name in ('acceleration_noise', 'command_noise', 'capability_noise'):
        value = getattr(setting, name)
        if value is not None:
            parameters[name] = float(value)
    data['parameters'] = parameters
    if setting.measurement_variance is not None:
        data['R'] = [[float(setting.measurement_variance)]]
    data['name'] = f"{data['name']}-tuned"
    data['description'] = f"{data.get('description', '')} (noise tuned by kf-train tune)"
    rail_preset_from_mapping(data, source='tuned preset')        # must load back
    return yaml.safe_dump(data, sort_keys=False, allow_unicode=True)


def default_preset_output(output: str) -> str:
    """Return where the tuned rail preset goes by default: PARAMS.yaml -> PARAMS-rail.yaml."""
    root, ext = os.path.splitext(output)
    return f'{root}-rail{ext or ".yaml"}'


def _number(value: float) -> str:
    """Return a number with 4 significant digits."""
    return 'inf' if math.isinf(value) else ('-' if value != value else f'{value:.4g}')


def _fit_lines(fit: RailFit, confidence: float) -> List[str]:
    """Return the estimates' table, the starts and, in words, what the data cannot tell."""
    lines = [f'maximum likelihood of the IMM innovations: {fit.passes} passes over the data '
             f'({fit.evaluations} settings), {fit.seconds:.1f} s; stopped: {fit.stop}']
    for s in fit.starts:
        lines.append(f'  climb from {s.label}: log-likelihood {s.start_log_likelihood:.2f} -> '
                     f'{s.log_likelihood:.2f} ({s.stop})')
    if not fit.improved:
        lines.append(f'  no setting beats the one in use (log-likelihood '
                     f'{fit.start_log_likelihood:.2f}) by {MIN_GAIN:g}: it is kept')
    lines.append(f'  {"parameter":<40} {"estimate":>10}  {f"{confidence:.0%} interval":<24}'
                 f'{"std. error":>10}')
    for e in fit.estimates:
        label = f'{e.parameter.symbol:<5} {e.parameter.name} [{e.parameter.unit}]'
        interval = (f'[{_number(e.low)}, {_number(e.high)}]' if e.identified
                    else 'the data cannot tell')
        lines.append(f'  {label:<40} {_number(e.value):>10}  {interval:<24}'
                     f'{_number(e.std_error):>10}')
    lines += [f'  {e.parameter.symbol}: {e.reason}' for e in fit.estimates if e.reason]
    return lines


def _consistency(run, k: int):
    """Return nis_consistency of setting k's fused innovations (gated fixes, holds left out)."""
    fused = ~run.gated[k] & np.isfinite(run.innovation[k]) if run.gated.shape[1] \
        else np.ones(run.nis.shape[1], dtype=bool)
    return nis_consistency(Innovations(run.innovation[k, fused][:, None],
                                       run.variance[k, fused][:, None, None]),
                           CHECK_CONFIDENCE)


def _check_lines(run, b, a) -> List[str]:
    """Return ℓ, the NIS and whiteness lines of the node's run of [start, tuned]: b, a."""
    ll = run.log_likelihood
    lines = [f'log-likelihood: before {ll[0]:.2f}, after {ll[1]:.2f}',
             f'NIS, mean of {a.count} mixture innovations the node fused ({CHECK_CONFIDENCE:.0%}'
             f' χ² bounds [{a.low:.4g}, {a.high:.4g}]): before {b.mean_nis:.4g} ({b.verdict}),'
             f' after {a.mean_nis:.4g} ({a.verdict})',
             f'fixes the χ² gate rejected: before {int(run.gated_count[0])}, after '
             f'{int(run.gated_count[1])}',
             f'lag-1 autocorrelation of the innovations ({CHECK_CONFIDENCE:.0%} bound '
             f'±{a.lag1_bound:.3g}): before {b.lag1:.3g}, after {a.lag1:.3g}']
    return lines + [f'verdict: {sentence}' for sentence in model_verdict(a)]


def _setup(args: TuneOptions, preset: RailPreset, noises: List[str], data):
    """
    Return (data, notes, fixed setting, names estimated, start setting, R written?).

    A bag's rows carry their variances, and the node uses each (times its learned
    scale): the fit does too, and estimates no R (measurement_variance None) unless
    ``--estimate-r``. A table carries none: R is its second differences' estimate
    (:func:`_moment_variance`), or ``--fix-r``'s; the node untuned uses the preset's R.
    It is fitted only where the node keeps it (``noise_window`` 0) or ``--estimate-r``
    asks: a node that learns a scale s on R online uses s·R, so R sets only where s
    starts, and the likelihood's curvature in it comes from the first fixes' transient
    (on simulated white runs its 95 % interval missed the truth in 2 of 3 seeds).
    """
    carried, note = carried_variances(data, args.estimate_r)
    rows_carry = data.measurement_variances is not None and not args.estimate_r
    if rows_carry and carried is None:
        low, high = (float(f(data.measurement_variances)) for f in (np.min, np.max))
        note = (f'the messages carry varying variances ({low:.4g} to {high:.4g}): the node '
                'uses each, times its learned scale, and so does the fit (--estimate-r '
                'estimates one R instead)')
    notes = [line for line in (data.summary, note) if line]
    params = preset.parameters
    if args.fix_r is not None:
        start_r = args.fix_r[0]
    elif rows_carry:
        start_r = None                                       # the rows' own variances
    else:
        start_r = _moment_variance(data.segments)
    learns = params.noise_window > 0
    estimate_r = args.fix_r is None and not rows_carry and (args.estimate_r or not learns)
    if args.fix_r is None and not rows_carry and not estimate_r:
        notes.append(f'R is not fitted: the node learns a scale on it online (noise_window '
                     f'{params.noise_window:g}), so R sets only where that scale starts; the '
                     f'second differences give {start_r:.4g} m², written as that start '
                     '(--estimate-r fits it)')
    names = list(noises) + (['measurement_variance'] if estimate_r else [])
    fixed = RailNoise(params.acceleration_noise, params.command_noise, params.capability_noise,
                      start_r)
    before = fixed._replace(measurement_variance=None if rows_carry
                            else params.noise_std_m ** 2)
    return data, notes, fixed, names, before, args.fix_r is not None or not rows_carry


def _comments(args: TuneOptions, fit: RailFit, rows: int, spec_label: str, preset_output: str,
              notes: List[str]) -> List[str]:
    """Return the params file's leading comments."""
    use = os.path.basename(args.output)
    comments = [f'Written by kf-train tune on {datetime.date.today().isoformat()} from '
                f'{args.input} ({rows} innovations), preset {spec_label}: the tuned rail '
                f'preset is {os.path.basename(preset_output)}.']
    comments += [f'{e.parameter.name} = {_number(e.value)}, {args.confidence:.0%} interval '
                 f'[{_number(e.low)}, {_number(e.high)}]' for e in fit.estimates]
    comments += [f'input: {line}' for line in notes]
    comments.append(f'Use: estimator --ros-args --params-file {use} (or kf-train replay BAG '
                    f'--params-file {use})')
    return comments


def tune_rail(args: TuneOptions, preset: RailPreset, noises: List[str], spec_label: str) -> str:
    """Estimate, check, write the files; return the report (ValueError for bad input)."""
    if args.output == '-' and not args.preset_output:
        raise ValueError('--preset-output is needed with --output - (the params file '
                         'points at the tuned rail preset file)')
    preset_output = args.preset_output or default_preset_output(args.output)
    for target in (args.output, preset_output):
        if target != '-':
            check_output_path(target)       # before minutes of work, not after
    topics = TopicOptions(args.topic, args.control_topic, args.truth_topic)
    full = reader_for(args.input)(args.input, preset, topics)
    holdout = split_holdout(full.segments, args.holdout)
    other = (reader_for(args.validate)(args.validate, preset, topics) if args.validate
             else None)                     # read before the fit: a bad path fails fast
    data, notes, fixed, names, before, r_written = _setup(
        args, preset, noises, training_input(full, holdout))    # the fit sees no held-out row
    segments = data.segments
    rows = sum(max(s.t_s.shape[0] - 1, 0) for s in segments)
    if rows < 2:
        raise ValueError('no innovations to estimate from: the data need at least 3 rows')
    base = preset.parameters

    # The node's own likelihood: the rows' variances, its learned scale on R, its gate.
    variances = segment_variances(segments, data.measurement_variances)
    gate = chi2_quantile(node_settings(preset.source).gate_probability, 1)

    def likelihoods(settings):
        return rail_log_likelihoods(base, segments, settings, variances=variances,
                                    adaptation=base.adaptation(),
                                    gate_threshold=gate).log_likelihood

    shipped = load_rail_preset().parameters          # the grid's centre, however started
    defaults = fixed._replace(acceleration_noise=shipped.acceleration_noise,
                              command_noise=shipped.command_noise,
                              capability_noise=shipped.capability_noise)
    fit = fit_rail_noise(likelihoods, names, fixed, fixed, rows, args.confidence,
                         other_starts=[] if defaults == fixed else [('the defaults', defaults)],
                         grid_centre=defaults, start_label=spec_label)
    run = rail_log_likelihoods(base, segments, [before, fit.setting], variances=variances,
                               adaptation=base.adaptation(), gate_threshold=gate,
                               innovations=True)
    checks = _consistency(run, 0), _consistency(run, 1)
    params = {'preset': os.path.abspath(preset_output)}
    if r_written:
        params['measurement_variance'] = float(fit.setting.measurement_variance)
    text = '\n'.join(
        [f'kf-train tune: preset {spec_label} (rail IMM), {rows + len(segments)} rows '
         f'({len(segments)} object{"s" * (len(segments) != 1)}), {rows} innovations, '
         'initialization first_measurement']
        + [f'input: {line}' for line in notes] + _fit_lines(fit, args.confidence)
        + _check_lines(run, *checks))
    # The messages' R stays theirs: the preset file keeps its own R then.
    written = fit.setting if r_written else fit.setting._replace(measurement_variance=None)
    tuned = (preset._replace(parameters=written.parameters(base)),
             params.get('measurement_variance', 0.0))
    lines, refused = _validation(args, preset, tuned, (full, holdout), other,
                                 inconsistent_reason(*checks))
    text = '\n'.join([text] + lines)
    if refused:
        return text + f'\nkept the start: {refused}; nothing written (--force writes it)'
    write_atomic(preset_output, [tuned_rail_yaml(preset, written)])
    comments = _comments(args, fit, rows, spec_label, preset_output, notes)
    write_atomic(args.output, [params_yaml(params, comments)])
    return text + f'\nwrote {args.output} and {preset_output}'


def _validation(args: TuneOptions, preset: RailPreset, tuned: tuple,
                held_out: Tuple[TuneInput, Holdout], other: Optional[TuneInput],
                inconsistent: Optional[str] = None) -> Tuple[List[str], Optional[str]]:
    """
    Return (the report's validation lines, why the tuned setting is refused or None).

    The start is the node untuned (the preset, the rows' own variances); the tuned
    setting is what the written files make the node run. Both are scored on the
    held-out windows and on ``--validate``'s input (whole, after the warm-up).
    ``inconsistent``: why the fit's own innovations refuse it (inconsistent_reason).
    """
    comparisons, lines = [], []
    full, holdout = held_out
    if args.holdout > 0.0:
        if holdout.kept_whole:
            lines.append(f'held-out: {holdout.kept_whole} segment(s) shorter than '
                         f'{MIN_SPLIT_S:g} s kept whole for the fit')
        if any(w is not None for w in holdout.windows):
            comparisons.append(_compare(f'held-out (last {100 * args.holdout:g} %)', preset,
                                        tuned, full, holdout.windows))
    if other is not None:
        comparisons.append(_compare(f'{os.path.basename(args.validate)} (after '
                                    f'{RAIL_WARMUP_S:g} s)', preset, tuned, other,
                                    warm_windows(other.segments)))
    for comparison in comparisons:
        lines += comparison_lines(comparison)
    reasons = [r for r in [inconsistent, *map(worse_reason, comparisons)] if r]
    if reasons and args.force:
        lines.append(f'--force: written although {reasons[0]}')
    return lines, None if args.force or not reasons else reasons[0]


def _compare(label: str, preset: RailPreset, tuned: tuple, data, windows) -> Comparison:
    """Return the start and the tuned setting scored by the node on ``windows``."""
    variances = segment_variances(data.segments, data.measurement_variances)
    return Comparison(label, score_setting(preset, data.segments, windows, variances),
                      score_setting(tuned[0], data.segments, windows, variances, tuned[1]))


def rail_preset_of(args: TuneOptions) -> Optional[RailPreset]:
    """Return the rail preset ``args`` choose (--preset rail or a rail --config), else None."""
    if args.config:
        return load_rail_preset(args.config) if is_rail_preset_file(args.config) else None
    return load_rail_preset() if args.preset in (None, RAIL_PRESET_NAME) else None

"""
The estimator node's ``/diagnostics`` status, built from plain data.

Pure (no rclpy, no message package): :func:`filter_status` reads the streaming estimator
and the node's counters and returns the level, the message and the key/value pairs;
:func:`kf_train.ros.messages.to_diagnostics_msg` makes the message of them. The values
are strings, formatted as the status has always shown them.
"""

import functools
import math
from typing import List, NamedTuple, Optional, Sequence, Tuple

from kf_train.filters import chi2_mean_bounds, PARTICLE_KINDS
import numpy as np

CONSISTENCY_CONFIDENCE = 0.99
"""Two-sided confidence of the bounds on the mean NIS."""
MAX_CONDITION = 1e12
"""Condition number of P above which the status warns: beyond ~1e12 a double keeps only a
few significant digits of the smaller eigen-direction."""
STATUS_SUFFIX = 'filter'
"""The estimator's status is named '<node name>: filter'."""
MATCHED_KEYS = ('measurement_publishers', 'estimate_subscribers', 'prediction_subscribers')
"""Keys counting the DDS endpoints matched on the node's side of measurement, estimate and
prediction (the node adds them: only it can count them)."""


class NodeCounts(NamedTuple):
    """What the node counted itself (the estimator counts the rest)."""

    received: int
    fused: int
    rejected: int
    set_state_refused: int
    controls_received: int
    controls_rejected: int


class Activity(NamedTuple):
    """The input's pace since the last status."""

    input_rate_hz: float
    fused_rate_hz: float
    age_s: float
    """Time since the last fused measurement (since the start if none was fused)."""
    ever_fused: bool


class FilterStatus(NamedTuple):
    """One diagnostic status: level, message, values."""

    level: str
    """'OK' or 'WARN'."""
    message: str
    values: List[Tuple[str, str]]
    timeout_warning: Optional[str]
    """The timeout text when no measurement was fused for timeout_s, else None."""


@functools.lru_cache(maxsize=1024)
def nis_bounds(count: int, dim_z: int) -> Tuple[float, float]:
    """Return the CONSISTENCY_CONFIDENCE bounds of the mean of count NIS values (dim_z each)."""
    return chi2_mean_bounds(count, dim_z, CONSISTENCY_CONFIDENCE)


def filter_status(estimator, counts: NodeCounts, activity: Activity, timeout_s: float,
                  nis: Sequence[float]) -> FilterStatus:
    """
    Return the status of ``estimator`` (a streaming estimator) and the node around it.

    WARN, with every reason joined by '; ', when no measurement was fused for
    ``timeout_s``, when the mean of the ``nis`` window leaves its 99% bounds (noise
    parameters too small or too large), or when the covariance is ill-conditioned.
    """
    warnings = []
    timeout_warning = None
    if activity.age_s > timeout_s:
        what = 'no measurement fused' if activity.ever_fused else 'no measurement fused yet'
        timeout_warning = f'{what} for {activity.age_s:.1f} s (timeout_s {timeout_s:g})'
        warnings.append(timeout_warning)
    values = [
        ('preset', estimator.preset.name),
        ('filter', estimator.settings.filter),
        ('initialized', str(estimator.initialized).lower()),
        ('input_rate_hz', f'{activity.input_rate_hz:.3f}'),
        ('fused_rate_hz', f'{activity.fused_rate_hz:.3f}'),
        ('last_measurement_age_s', f'{activity.age_s:.3f}' if activity.ever_fused
         else 'never'),
    ]
    values += _count_values(estimator, counts)
    values += _filter_values(estimator)
    values += regime_values(estimator)
    nis_values, nis_warning = _nis_values(nis, estimator.model.dim_z)
    values += nis_values
    warnings += [nis_warning] if nis_warning else []
    state = estimator.state
    if state is not None:
        condition = condition_number(state[1])
        values.append(('covariance_condition', f'{condition:.6g}'))
        if not condition <= MAX_CONDITION:
            warnings.append(f'ill-conditioned covariance (condition {condition:.3g})')
    if warnings:
        return FilterStatus('WARN', '; '.join(warnings), values, timeout_warning)
    message = 'ok' if estimator.initialized else 'waiting for measurements'
    return FilterStatus('OK', message, values, timeout_warning)


def gate_reach_m(estimator, now_ns: int, variances: Sequence[float]) -> float:
    """
    Return the smallest position jump the gate would reject now [m] (inf: no gate).

    With S the innovation covariance of a measurement at ``now_ns`` (in the stamps'
    time base; the newest stamp if that is later) and R from a message's
    ``variances`` as the node fuses them, a jump d of the position alone from the
    predicted one has NIS d² (S⁻¹)₀₀, so the gate (NIS > threshold) rejects it from
    d = sqrt(threshold / (S⁻¹)₀₀): sqrt(threshold · S) for a position. The measured
    states are the first ones (position, then velocity). For a model with regimes (the
    rail IMM) S is its mixture's, from the model's own pure fused step (S does not
    depend on z); for the others the state's look-ahead (what predict_to publishes).
    Nothing changes.
    """
    threshold = estimator.gate_threshold
    if not math.isfinite(threshold):
        return math.inf
    R = estimator.measurement_noise(*variances)
    m = R.shape[0]
    stamp_ns = max(now_ns, estimator.last_stamp_ns)
    if regime_names(estimator):
        x, P = estimator.state
        dt_s = (stamp_ns - estimator.last_stamp_ns) / 1e9
        S = estimator.model.predict_update(x, P, dt_s, np.zeros(m), R)[2].innovation_covariance
    else:
        _, P = estimator.predict_to(stamp_ns)
        S = P[:m, :m] + R
    return math.sqrt(threshold / float(np.linalg.inv(S)[0, 0]))


def condition_number(P) -> float:
    """Return ``np.linalg.cond(P)``: its SVD and division, without its overheads (~8 µs)."""
    s = np.linalg.svd(P, compute_uv=False).tolist()
    if s[-1] > 0.0 and math.isfinite(s[0]):
        return s[0] / s[-1]                 # the same IEEE division as numpy's
    return float(np.linalg.cond(P))         # singular, non-finite: numpy's conventions


def _count_values(estimator, counts: NodeCounts) -> List[Tuple[str, str]]:
    """Return the counts: received, fused, rejections, resets, controls."""
    stats = estimator.stats()
    values = [('received', str(counts.received)), ('fused', str(counts.fused)),
              ('fused_out_of_sequence', str(stats.out_of_sequence)),
              ('rejected', str(counts.rejected))]
    values += [(f'rejected.{reason}', str(count))
               for reason, count in stats.rejections.items()]
    resets = stats.resets
    values.append(('resets', str(sum(resets.values()))))
    values += [(f'resets.{reason}', str(count)) for reason, count in resets.items()]
    values.append(('reacquisitions', str(stats.reacquisitions)))   # lock-outs, track kept
    values.append(('set_state_refused', str(counts.set_state_refused)))
    if estimator.has_control:
        values.append(('controls_received', str(counts.controls_received)))
        values += [(f'controls.{key}', str(count)) for key, count in stats.controls.items()]
        values.append(('controls_rejected', str(counts.controls_rejected)))
        values += [(f'controls_rejected.{reason}', str(count))
                   for reason, count in stats.control_rejections.items()]
    if estimator.fuses_velocity:  # the rail preset's speeds (StreamEstimator.process_velocity)
        values.append(('holds', str(stats.holds)))    # held positions fused as a standstill
        values += [(f'velocities_{key}', str(count)) for key, count in stats.velocities.items()]
        values += [(f'velocities_rejected.{reason}', str(count))
                   for reason, count in stats.velocity_rejections.items()]
    return values


def _filter_values(estimator) -> List[Tuple[str, str]]:
    """Return the filter's own figures (UKF regularisations, particle ESS) and the gate."""
    values = []
    model = estimator.model
    regularisations = getattr(model, 'regularisations', None)
    if regularisations is not None:
        values.append(('ukf_regularisations', str(regularisations)))
    if estimator.settings.filter in PARTICLE_KINDS and estimator.initialized:
        # The particles last stepped: those of the newest estimate.
        values += [('pf_ess', f'{model.filter.ess:.1f}'),
                   ('pf_resample_count', str(model.filter.resample_count))]
    values += [('gate_probability', f'{estimator.settings.gate_probability:g}'),
               ('gate_threshold', f'{estimator.gate_threshold:.6g}')]
    return values


def regime_names(estimator) -> Tuple[str, ...]:
    """Return the regimes of the estimator's model (the rail preset's IMM), else ()."""
    return estimator.model.mode_names


def regime_values(estimator) -> List[Tuple[str, str]]:
    """
    Return the regime values of a model with regimes: the likeliest, and each probability.

    ``regime`` (the likeliest regime's name; ``unknown`` before the first measurement)
    and ``regime.<name>`` (its probability after the newest fused measurement, 4
    decimals), ``measurement_noise_scale``, the scale the model learned on R
    (:meth:`~kf_train.estimator.StreamEstimator.noise_scale`), and
    ``measurement_error_walk_rate_hz``, the rate it learned for the receiver's slow
    error (:meth:`~kf_train.estimator.StreamEstimator.error_walk_rate_hz`). Nothing for
    a model without regimes.
    """
    names = regime_names(estimator)
    if not names:
        return []
    current = estimator.mode_probabilities()
    if current is None:
        return [('regime', 'unknown')]
    names, probabilities = current
    likeliest = names[int(np.argmax(probabilities))]
    values = [('regime', likeliest)] + [(f'regime.{name}', f'{float(p):.4f}')
                                        for name, p in zip(names, probabilities)]
    scale = estimator.noise_scale()
    if scale is not None:  # the learned scale on R: visible as it adapts
        values.append(('measurement_noise_scale', f'{scale:.4g}'))
    walk_rate_hz = estimator.error_walk_rate_hz()
    if walk_rate_hz is not None:  # the receiver's slow error, learned: how fast it walks
        values.append(('measurement_error_walk_rate_hz', f'{walk_rate_hz:.4g}'))
    return values


def _nis_values(nis: Sequence[float],
                dim_z: int) -> Tuple[List[Tuple[str, str]], Optional[str]]:
    """Return the NIS window's values and, if its mean is out of bounds, the warning."""
    count = len(nis)
    values = [('nis_window_count', str(count))]
    if not count:
        return values, None
    mean = math.fsum(nis) / count
    lower, upper = nis_bounds(count, dim_z)
    values += [('nis_window_mean', f'{mean:.6g}'), ('nis_lower_99', f'{lower:.6g}'),
               ('nis_upper_99', f'{upper:.6g}')]
    if mean > upper:
        return values, (f'inconsistent: noise parameters too small (mean NIS {mean:.3g} > '
                        f'{upper:.3g} over {count} updates)')
    if mean < lower:
        return values, (f'inconsistent: noise parameters too large (mean NIS {mean:.3g} < '
                        f'{lower:.3g} over {count} updates)')
    return values, None


# ---------------------------------------------------------------------------
# The suggested process noise (kf_train.ros.noise_advice)
# ---------------------------------------------------------------------------

NOISE_WARNING = 'inconsistent: noise parameters too'
"""How the NIS warning above starts: where the advice on q is added to the message."""


def with_noise_suggestion(status: FilterStatus, suggestion, current_q: float,
                          span_s: float) -> FilterStatus:
    """
    Return ``status`` with the q the recent window suggests (a NoiseSuggestion, or None).

    Keys: ``suggested_process_noise_density`` [m²/s³], its 95 % interval
    ``suggested_process_noise_density_low_95`` / ``_high_95`` (low 0 when the window
    cannot tell q from 0; high inf when it cannot bound it), the window
    (``suggested_process_noise_window``: innovations; ``..._window_s``: seconds) and
    ``process_noise_advice`` (which way and how far to move ``process_noise_density``).
    The message ends with that advice when ``current_q`` is outside the interval (the
    NIS window cannot see a q far too large: the filter's innovations then stay about
    as large as it predicts), and when the NIS check warns that the noise is too small
    or too large (with q inside the interval: then R is the suspect). The level is not
    changed: the NIS check decides it. No suggestion (None): the status as it is,
    without these keys.
    """
    if suggestion is None:
        return status
    advice = suggestion.advice(current_q)
    values = list(status.values) + [
        ('suggested_process_noise_density', f'{suggestion.process_noise_density:.6g}'),
        ('suggested_process_noise_density_low_95', f'{suggestion.low:.6g}'),
        ('suggested_process_noise_density_high_95', f'{suggestion.high:.6g}'),
        ('suggested_process_noise_window', str(suggestion.count)),
        ('suggested_process_noise_window_s', f'{span_s:.3f}'),
        ('process_noise_advice', advice)]
    message = status.message
    if not suggestion.low <= current_q <= suggestion.high:
        message = f'{message}; {advice}'
    elif NOISE_WARNING in message:
        message = f'{message}; {advice}: check the measurement variance R'
    return FilterStatus(status.level, message, values, status.timeout_warning)

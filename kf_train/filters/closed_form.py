"""
The 2-state train step in closed form, in plain Python floats: the equations' one home.

The model is the one :mod:`kf_train.filters.models` builds for the train: state
[position m, velocity m/s], ``F(dt) = [[1, dt], [0, 1]]``, a position measurement
``H = [1, 0]`` with scalar variance R, and process noise entries (Q00, Q01, Q11) of
Q(dt). Its reference is the generic n-state path, :func:`kf_train.filters.kalman.predict`
and :func:`kf_train.filters.kalman.update` with those matrices: the results are the
same to rounding (the tests hold them to 1e-9).

The update is the generic path's Joseph form, P = (I - K H) P⁻ (I - K H)ᵀ + K R Kᵀ,
written out for this H and the optimal K, where it reduces exactly to
P00 = a·P⁻00, P01 = a·P⁻01, P11 = P⁻11 - K1·P⁻01 with a = 1 - K0 = R/S. Taking
a = R/S rather than 1 - K0 avoids the cancellation when R ≪ P⁻00, and keeps P00 >= 0
in floating point.

Floats in, floats out, unchecked: callers check their inputs and the results. The
estimator's closed-form train model (:mod:`kf_train.estimator.adapters`) and
``FastTrainFilter.predict``/``update`` call these functions. Two hot loops transcribe
the arithmetic inline, operation for operation, because the calls and their tuples
cost more than the arithmetic (``make bench`` row 1, issue 22; the figures are beside
each copy): :meth:`~kf_train.filters.fast.FastTrainFilter.step` and the loop of
:meth:`~kf_train.filters.fast.FastTrainFilter.run`. There is no vectorised copy: many
trains at once run in the bank (:mod:`kf_train.batch.bank`, the generic n-state
arithmetic). Tests hold both copies to this module bit for bit
(test/unit/test_closed_form.py).
"""

from typing import Callable, NamedTuple, Tuple, Union

from kf_train.filters.models import (
    per_step_noise_terms, PerStepNoise, white_noise_terms, WhiteNoiseAcceleration)
from kf_train.filters.validation import as_covariance

State = Tuple[float, float, float, float, float]
"""(x0, x1, P00, P01, P11): position, velocity and the covariance's distinct entries."""

NoiseModel = Union[None, WhiteNoiseAcceleration, PerStepNoise, Callable[[float], object]]


class FastUpdate(NamedTuple):
    """The innovation statistics of one update, as plain floats."""

    innovation: float
    """y = z - x⁻[0] [m]."""
    innovation_variance: float
    """S = P⁻[0, 0] + R [m²]."""
    nis: float
    """y² / S."""
    gain: Tuple[float, float]
    """K = P⁻ Hᵀ / S."""


def predict(x0: float, x1: float, p00: float, p01: float, p11: float, dt: float,
            q00: float, q01: float, q11: float) -> State:
    """Return the prior (x0, x1, P00, P01, P11) dt seconds after the given state."""
    # x⁻ = F x;  P⁻ = F P Fᵀ + Q with F = [[1, dt], [0, 1]]:
    #   P⁻00 = P00 + dt (P01 + (P01 + dt P11)) + Q00
    #   P⁻01 = P01 + dt P11 + Q01;  P⁻11 = P11 + Q11
    p01_dt = p01 + dt * p11
    return (x0 + dt * x1, x1, p00 + dt * (p01 + p01_dt) + q00, p01_dt + q01, p11 + q11)


def correct(x0: float, x1: float, p00: float, p01: float, p11: float, z: float,
            R: float) -> Tuple[State, FastUpdate]:
    """
    Return the posterior (x0, x1, P00, P01, P11) and statistics of one update.

    The prior is [x0, x1] with covariance [[p00, p01], [p01, p11]]; z [m] is a
    position measurement of variance R [m²]. S = 0 raises ZeroDivisionError.
    """
    s = p00 + R                         # S = H P⁻ Hᵀ + R
    y = z - x0                          # y = z - H x⁻
    k0 = p00 / s                        # K = P⁻ Hᵀ / S
    k1 = p01 / s
    a = R / s                           # = 1 - k0, without the cancellation
    # The Joseph form for this optimal K and H = [1, 0], entry by entry (the second
    # forms use P⁻01 - k1 P⁻00 = a P⁻01 and R k0 = a P⁻00):
    #   P00 = a² P⁻00 + R k0² = a P⁻00
    #   P01 = a (P⁻01 - k1 P⁻00) + R k0 k1 = a P⁻01
    #   P11 = (P⁻11 - k1 P⁻01) - k1 (P⁻01 - k1 P⁻00) + R k1² = P⁻11 - k1 P⁻01
    posterior = (x0 + k0 * y, x1 + k1 * y, a * p00, a * p01, p11 - k1 * p01)
    return posterior, FastUpdate(y, s, y * y / s, (k0, k1))  # NIS = y² / S


def noise_terms_function(noise: NoiseModel) -> Callable[[float], Tuple[float, float, float]]:
    """
    Return a function dt -> (Q00, Q01, Q11) for a process-noise model.

    ``None`` means no process noise. A WhiteNoiseAcceleration or PerStepNoise is
    evaluated in closed form; any other callable dt -> 2x2 matrix is called and its
    result checked (symmetric, positive semi-definite), raising ValueError naming Q.
    """
    if noise is None:
        return lambda dt: (0.0, 0.0, 0.0)
    if type(noise) is WhiteNoiseAcceleration:
        q = float(noise.q)
        return lambda dt: white_noise_terms(q, dt)
    if type(noise) is PerStepNoise:
        a, c, b = (float(noise.Q_step[0, 0]), float(noise.Q_step[0, 1]),
                   float(noise.Q_step[1, 1]))
        period_s = float(noise.period_s)
        return lambda dt: per_step_noise_terms(a, c, b, period_s, dt)
    if not callable(noise):
        raise ValueError(f'noise must be None, WhiteNoiseAcceleration, PerStepNoise or a '
                         f'callable dt -> Q, got {noise!r}')

    def terms(dt: float) -> Tuple[float, float, float]:
        Q = as_covariance('Q', noise(dt), 2)
        return float(Q[0, 0]), float(Q[0, 1]), float(Q[1, 1])
    return terms

"""
A GNSS receiver that lies like one: the rail scenario's ``receiver`` error model (issue 24).

Calibrated to the statistics of two real logs of a regional train (u-blox M8N, 5 Hz;
docs/rail.md). Per epoch, :class:`GnssReceiver` turns the true along-track position
and speed into what such a receiver outputs (:class:`GnssFix`):

* **position** = truth + a slow, time-correlated error (an integrated, mean-reverting
  Ornstein-Uhlenbeck process, :mod:`kf_train.sim.gnss_error`, exact for any time step)
  + a small white part, + multipath jumps and the cold start's decaying error;
* **hold at standstill**: below ``hold_speed_mps`` the receiver repeats its previous
  position exactly with ``hold_probability``; the error keeps running underneath;
* **hAcc**, the reported accuracy: lognormal around ``h_acc_median_m``, slowly
  varying; not the true σ; up to ``cold_start_h_acc_m`` during a cold start;
* **Doppler speed** = true speed + a small smooth error (its own OU process, never
  the position error's velocity), with a reported ``speedAcc`` that overstates it;
* **artefacts**: dropped and repeated epochs, outages (no fixes), multipath jumps,
  a cold start and a speed dip, each with its rate or probability.

The calibration (a least-squares fit of :func:`model_structure_function` to the
statistics' D(τ), the mean square of runs A and B, in log D; T_x fixed at 100 s
since the table cannot tell it from infinity, and a bounded error is the physical
choice) gave σ_u = 0.145 m/s, T_u = 13.1 s, σ_w = 0.068 m, within 8 % of the table
from 0.2 s to 60 s. Everything is drawn from the generator handed in, a fixed number
of draws per epoch (plus a few when an artefact starts), so a seed gives one run.
"""

from dataclasses import dataclass, fields
import math
from typing import NamedTuple, Optional, Tuple

from kf_train.sim.gnss_error import (
    model_structure_function, ou_step, stationary_covariance, structure_function,
    transition_covariance)
import numpy as np

GNSS_MODELS = ('receiver', 'white')
"""The rail scenario's GNSS error models: this receiver, or the old white noise."""
DEFAULT_GNSS_MODEL = 'receiver'
"""The model of the simulator node and ``kf-train simulate`` (the library's batch
``rail_scenario`` and ``RailStream`` keep 'white', the development runs' model)."""
__all__ = ['DEFAULT_GNSS_MODEL', 'GNSS_MODELS', 'GnssFix', 'GnssReceiver',
           'GnssReceiverParameters', 'model_structure_function', 'structure_function']


@dataclass(frozen=True)
class GnssReceiverParameters:
    """The receiver's error model; defaults calibrated to the real logs (module doc)."""

    velocity_std_mps: float = 0.145
    """σ_u: stationary std of the slow error's velocity (0-10) [m/s]."""
    velocity_time_s: float = 13.1
    """T_u: correlation time of the slow error's velocity (0.1-1000) [s]."""
    revert_time_s: float = 100.0
    """T_x: time the slow error takes to revert to zero (1-10000) [s]."""
    white_std_m: float = 0.068
    """σ_w: std of the white, sample-to-sample part (0-100) [m]."""
    hold_speed_mps: float = 0.3
    """Below this true speed the receiver may hold its position (0-5) [m/s]."""
    hold_probability: float = 0.8
    """Probability that a standing fix repeats the previous position (0-1)."""
    h_acc_median_m: float = 2.1
    """Median of the reported hAcc in normal operation (0.01-100) [m]."""
    h_acc_log_std: float = 0.3
    """Std of ln hAcc around its median (0-3)."""
    h_acc_time_s: float = 60.0
    """Correlation time of ln hAcc (0.1-10000) [s]."""
    doppler_std_mps: float = 0.05
    """Std of the Doppler speed's smooth error (0-10) [m/s]."""
    doppler_time_s: float = 2.0
    """Correlation time of the Doppler speed's error (0.01-1000) [s]."""
    speed_acc_median_mps: float = 0.3
    """Median of the reported speedAcc (0.001-100) [m/s]."""
    speed_acc_log_std: float = 0.25
    """Std of ln speedAcc around its median (0-3)."""
    speed_acc_time_s: float = 30.0
    """Correlation time of ln speedAcc (0.1-10000) [s]."""
    drop_rate_per_s: float = 0.003
    """Rate of dropped epochs (no fix) (0-10) [1/s]."""
    repeat_rate_per_s: float = 0.003
    """Rate of repeated epochs (the previous fix again, exactly) (0-10) [1/s]."""
    outage_rate_per_h: float = 0.3
    """Rate of outages (a tunnel: no fixes at all) (0-1000) [1/h]."""
    outage_duration_s: float = 30.0
    """Length of an outage (0-3600) [s]."""
    multipath_rate_per_h: float = 1.0
    """Rate of multipath jumps (0-1000) [1/h]."""
    multipath_offset_m: Tuple[float, float] = (3.0, 30.0)
    """Range of a jump's size, drawn uniformly, random sign (0-10000) [m]."""
    multipath_duration_s: Tuple[float, float] = (2.0, 10.0)
    """Range of a jump's length, drawn uniformly (0-3600) [s]."""
    cold_start_probability: float = 0.5
    """Probability that a run begins with a cold start (0-1)."""
    cold_start_duration_s: float = 100.0
    """Length of a cold start (1-3600) [s]."""
    cold_start_h_acc_m: float = 1000.0
    """hAcc at the first fix of a cold start, decaying log-linearly (1-1e5) [m]."""
    cold_start_error_fraction: float = 0.3
    """The cold start's extra error, per std normal, as a fraction of its hAcc excess (0-1)."""
    speed_dip_rate_per_h: float = 0.3
    """Rate of speed dips (0-1000) [1/h]."""
    speed_dip_mps: float = 3.5
    """Depth of a speed dip, subtracted from the Doppler speed (0-100) [m/s]."""
    speed_dip_duration_s: float = 3.0
    """Length of a speed dip (a half-sine) (0.1-60) [s]."""
    speed_dip_speed_acc_mps: float = 1.1
    """speedAcc at the bottom of a speed dip (0-100) [m/s]."""

    def __post_init__(self):
        """Check every value against the range its docstring gives."""
        for field in fields(self):
            low, high = _RANGES[field.name]
            value = getattr(self, field.name)
            if isinstance(value, tuple):
                checked = tuple(_checked(f'{field.name}[{i}]', v, low, high)
                                for i, v in enumerate(value))
                if len(checked) != 2 or checked[0] > checked[1]:
                    raise ValueError(f'{field.name} must be (min, max), got {value!r}')
                object.__setattr__(self, field.name, checked)
            else:
                object.__setattr__(self, field.name, _checked(field.name, value, low, high))

    def structure_function(self, tau_s) -> np.ndarray:
        """Return the model's D(τ) [m] of the position error without artefacts."""
        return model_structure_function(tau_s, self.velocity_std_mps, self.velocity_time_s,
                                        self.revert_time_s, self.white_std_m)


_RANGES = {
    'velocity_std_mps': (0.0, 10.0), 'velocity_time_s': (0.1, 1000.0),
    'revert_time_s': (1.0, 1e4), 'white_std_m': (0.0, 100.0), 'hold_speed_mps': (0.0, 5.0),
    'hold_probability': (0.0, 1.0), 'h_acc_median_m': (0.01, 100.0),
    'h_acc_log_std': (0.0, 3.0), 'h_acc_time_s': (0.1, 1e4), 'doppler_std_mps': (0.0, 10.0),
    'doppler_time_s': (0.01, 1000.0), 'speed_acc_median_mps': (0.001, 100.0),
    'speed_acc_log_std': (0.0, 3.0), 'speed_acc_time_s': (0.1, 1e4),
    'drop_rate_per_s': (0.0, 10.0), 'repeat_rate_per_s': (0.0, 10.0),
    'outage_rate_per_h': (0.0, 1000.0), 'outage_duration_s': (0.0, 3600.0),
    'multipath_rate_per_h': (0.0, 1000.0), 'multipath_offset_m': (0.0, 1e4),
    'multipath_duration_s': (0.0, 3600.0), 'cold_start_probability': (0.0, 1.0),
    'cold_start_duration_s': (1.0, 3600.0), 'cold_start_h_acc_m': (1.0, 1e5),
    'cold_start_error_fraction': (0.0, 1.0), 'speed_dip_rate_per_h': (0.0, 1000.0),
    'speed_dip_mps': (0.0, 100.0), 'speed_dip_duration_s': (0.1, 60.0),
    'speed_dip_speed_acc_mps': (0.0, 100.0)}


def _checked(name: str, value, low: float, high: float) -> float:
    """Return value as a float in [low, high], else raise ValueError naming it."""
    if isinstance(value, bool) or not isinstance(value, (int, float, np.floating,
                                                         np.integer)):
        raise ValueError(f'{name} must be a number, got {value!r}')
    number = float(value)
    if not low <= number <= high:  # also rejects NaN
        raise ValueError(f'{name} must be in [{low:g}, {high:g}], got {value!r}')
    return number


class GnssFix(NamedTuple):
    """What the receiver outputs at one epoch; every field None when there is no fix."""

    position_m: Optional[float]
    h_acc_m: Optional[float]
    """Reported horizontal accuracy [m]; its square is the variance a driver publishes."""
    speed_mps: Optional[float]
    """Doppler speed along the track [m/s] (signed: a dip may take it below 0)."""
    speed_acc_mps: Optional[float]
    """Reported speed accuracy [m/s]."""


NO_FIX = GnssFix(None, None, None, None)


class _Event:
    """An artefact in progress: when it ends and its size."""

    def __init__(self, start_s: float, duration_s: float, size: float = 0.0):
        """Keep the start, the end and the size."""
        self.start_s, self.end_s, self.size = start_s, start_s + duration_s, size

    def active(self, t_s: float) -> bool:
        """Return whether t_s is within the event."""
        return self.start_s <= t_s < self.end_s


class GnssReceiver:
    """A seeded receiver: :meth:`fix` per epoch, in increasing time, any spacing."""

    def __init__(self, parameters: GnssReceiverParameters, rng: np.random.Generator):
        """Draw the initial (stationary) error state and whether the run cold-starts."""
        if not isinstance(parameters, GnssReceiverParameters):
            raise ValueError('parameters must be GnssReceiverParameters, got '
                             f'{type(parameters).__name__}')
        self.parameters = p = parameters
        self._rng = rng
        # Start in the stationary distribution: x and u correlated as P∞ says.
        self._state = _cholesky(stationary_covariance(
            p.velocity_std_mps, p.velocity_time_s, p.revert_time_s)) @ rng.standard_normal(2)
        # Unit OU processes of ln hAcc, ln speedAcc and the Doppler error.
        self._slow = rng.standard_normal(3)
        self._cold = rng.random() < p.cold_start_probability
        self._cold_offset = float(rng.standard_normal())
        self._t_s: Optional[float] = None
        self._start_s: Optional[float] = None
        self._last = NO_FIX
        self._events = {}
        self._step = None

    def _advance(self, dt_s: float, draws: np.ndarray) -> None:
        """Run the error processes on by dt: exact steps, 5 normals whatever dt."""
        if self._step is None or self._step[0] != dt_s:  # a periodic stream: computed once
            p = self.parameters
            phi, q = transition_covariance(dt_s, p.velocity_std_mps, p.velocity_time_s,
                                           p.revert_time_s)
            steps = [ou_step(dt_s, time_s) for time_s
                     in (p.h_acc_time_s, p.speed_acc_time_s, p.doppler_time_s)]
            self._step = (dt_s, phi, _cholesky(q), np.array(steps))
        _, phi, root, steps = self._step
        self._state = phi @ self._state + root @ draws[:2]
        self._slow = steps[:, 0] * self._slow + steps[:, 1] * draws[2:5]

    def _start_events(self, t_s: float, dt_s: float, chances: np.ndarray) -> None:
        """Start an outage, a multipath jump or a speed dip with their rates per dt."""
        p, rng = self.parameters, self._rng
        rates = {'outage': p.outage_rate_per_h / 3600.0,
                 'multipath': p.multipath_rate_per_h / 3600.0,
                 'dip': p.speed_dip_rate_per_h / 3600.0}
        for chance, (name, rate) in zip(chances, rates.items()):
            if self._active(name, t_s) is not None or chance >= rate * dt_s:
                continue
            if name == 'outage':
                self._events[name] = _Event(t_s, p.outage_duration_s)
            elif name == 'multipath':
                size = rng.uniform(*p.multipath_offset_m) * (1.0 if rng.random() < 0.5
                                                             else -1.0)
                self._events[name] = _Event(t_s, rng.uniform(*p.multipath_duration_s), size)
            else:
                self._events[name] = _Event(t_s, p.speed_dip_duration_s)

    def _active(self, name: str, t_s: float) -> Optional[_Event]:
        """Return the event ``name`` if it is in progress at t_s."""
        event = self._events.get(name)
        return event if event is not None and event.active(t_s) else None

    def fix(self, t_s: float, true_position_m: float, true_speed_mps: float) -> GnssFix:
        """Return the receiver's output at t_s for the true position and speed."""
        p = self.parameters
        draws, chances = self._rng.standard_normal(6), self._rng.random(6)
        if self._t_s is None:
            self._t_s = self._start_s = float(t_s)
            dt = 0.0
        else:
            dt = float(t_s) - self._t_s
            if not dt >= 0.0:
                raise ValueError(f'fix times must not decrease, got {t_s} after {self._t_s}')
            self._t_s = float(t_s)
            self._advance(dt, draws)
        hold, drop, repeat = chances[:3]
        self._start_events(t_s, dt, chances[3:])
        if self._active('outage', t_s) or drop < p.drop_rate_per_s * dt:
            return NO_FIX
        if repeat < p.repeat_rate_per_s * dt and self._last.position_m is not None:
            return self._last
        h_acc = p.h_acc_median_m * math.exp(p.h_acc_log_std * self._slow[0])
        error = float(self._state[0]) + p.white_std_m * draws[5]
        since = t_s - self._start_s
        if self._cold and since < p.cold_start_duration_s:
            # hAcc decays log-linearly from cold_start_h_acc_m; the error with its excess.
            cold = p.cold_start_h_acc_m * (h_acc / p.cold_start_h_acc_m) ** (
                since / p.cold_start_duration_s)
            error += p.cold_start_error_fraction * max(cold - h_acc, 0.0) * self._cold_offset
            h_acc = max(cold, h_acc)
        jump = self._active('multipath', t_s)
        if jump is not None:
            error += jump.size
        position = true_position_m + error
        if (true_speed_mps < p.hold_speed_mps and self._last.position_m is not None
                and hold < p.hold_probability):
            position = self._last.position_m
        speed = true_speed_mps + p.doppler_std_mps * self._slow[2]
        speed_acc = p.speed_acc_median_mps * math.exp(p.speed_acc_log_std * self._slow[1])
        dip = self._active('dip', t_s)
        if dip is not None:
            shape = math.sin(math.pi * (t_s - dip.start_s) / p.speed_dip_duration_s)
            speed -= p.speed_dip_mps * shape
            speed_acc = max(speed_acc, speed_acc + (p.speed_dip_speed_acc_mps - speed_acc)
                            * shape)
        self._last = GnssFix(float(position), float(h_acc), float(speed), float(speed_acc))
        return self._last


def _cholesky(q: np.ndarray) -> np.ndarray:
    """Return the lower L with L Lᵀ = q for a 2x2 PSD q (rounding clipped at 0)."""
    first = math.sqrt(max(q[0, 0], 0.0))
    cross = q[1, 0] / first if first > 0.0 else 0.0
    return np.array([[first, 0.0], [cross, math.sqrt(max(q[1, 1] - cross * cross, 0.0))]])

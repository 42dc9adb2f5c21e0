"""
A rail run (:mod:`kf_train.sim.rail`) as a sample-by-sample stream, for the simulator node.

:func:`rail_parameters` gives a run's values: drawn by a family (``metro``,
``regional``) from the seed, as :func:`kf_train.sim.rail.family_parameters` draws
them, with any of acceleration, braking, jerk, line speed, station spacing, dwell and
the cruise's texture given explicitly instead. :class:`RailStream` samples that run
at t_k = k / rate_hz (k = 1, 2, ...) for as long as it is asked to: it plans station
after station as the time comes, from the same generator in the same order as
:func:`kf_train.sim.rail.rail_run`, and draws the measurement noise one sample at a
time from the same generator as :func:`kf_train.sim.rail.rail_scenario`. So the
stream of a seed and its parameters gives exactly the numbers of
``rail_scenario(seed, parameters=...)`` (to the last bit), and goes on after its
``duration_s``. Every sample carries the true acceleration too.

``gnss_model`` chooses the position measurement as ``rail_scenario`` does: 'white'
(σ = ``noise_std_m``) or 'receiver' (:mod:`kf_train.sim.gnss_receiver`, from the
same generator, so again the numbers of ``rail_scenario(seed, ...,
gnss_model='receiver')``). A receiver's sample carries its reported variance hAcc²,
the Doppler speed and its variance speedAcc²; its ``measured_position_m`` is None
at an epoch without a fix (dropped, or in an outage).
"""

import dataclasses
from typing import Optional, Sequence

from kf_train.sim.gnss_receiver import GnssReceiverParameters
from kf_train.sim.rail import (  # the planner's steps: this module plans lazily
    _Plan, _plan_section, _streams, DEFAULT_FAMILY, family_parameters, gnss_receiver,
    RailParameters, RailRun)
from kf_train.sim.sample import ScenarioSample
import numpy as np

RAIL_FAMILIES = ('metro', 'regional')
"""The families a stream draws its values from (kf_train.sim.rail.FAMILIES)."""
PLAN_AHEAD_S = 10.0
"""How far past the newest sample the run is planned [s] (rail_run's margin)."""


def _pair(name: str, value) -> Optional[tuple]:
    """Return a (min, max) pair, None for None or an empty sequence."""
    if value is None or len(value) == 0:
        return None
    if len(value) != 2:
        raise ValueError(f'{name} must be [min, max], got {list(value)!r}')
    return float(value[0]), float(value[1])


def rail_parameters(family: str = DEFAULT_FAMILY, seed: int = 0, *,
                    accel_mps2: Optional[float] = None, brake_mps2: Optional[float] = None,
                    jerk_mps3: Optional[float] = None, line_speed_mps: Optional[float] = None,
                    station_spacing_m: Optional[Sequence[float]] = None,
                    dwell_s: Optional[Sequence[float]] = None,
                    texture_speed_mps: Optional[float] = None) -> RailParameters:
    """
    Return the values of the run ``family`` draws for ``seed``, with the given ones instead.

    None (or an empty sequence) keeps the drawn value; the others replace it and are
    checked against the ranges of :class:`~kf_train.sim.rail.RailParameters`
    (ValueError naming the value).
    """
    drawn = family_parameters(family, seed)
    given = {'accel_mps2': accel_mps2, 'brake_mps2': brake_mps2, 'jerk_mps3': jerk_mps3,
             'line_speed_mps': line_speed_mps,
             'station_spacing_m': _pair('station_spacing_m', station_spacing_m),
             'dwell_s': _pair('dwell_s', dwell_s), 'texture_speed_mps': texture_speed_mps}
    return dataclasses.replace(drawn, **{k: v for k, v in given.items() if v is not None})


def _square(value: Optional[float]) -> Optional[float]:
    """Return value², None for None (an accuracy's variance)."""
    return None if value is None else value * value


class RailStream:
    """A rail run measured at rate_hz with noise σ, sample by sample (see the module doc)."""

    def __init__(self, rate_hz: float, seed: Optional[int], noise_std_m: float = 1.0,
                 initial_position_m: float = 0.0,
                 parameters: Optional[RailParameters] = None, family: str = DEFAULT_FAMILY,
                 gnss_model: str = 'white',
                 receiver: Optional[GnssReceiverParameters] = None):
        """
        Plan the run of ``seed`` (None: fresh entropy) with ``parameters``.

        Without ``parameters`` the family draws them from the seed. The truth is
        shifted by ``initial_position_m``. ``gnss_model``: 'white' or 'receiver'
        (``receiver``: its parameters; noise_std_m is then not used).
        """
        rate_hz = float(rate_hz)
        if not rate_hz > 0.0:
            raise ValueError(f'rate_hz must be > 0, got {rate_hz}')
        if seed is None:
            seed = int(np.random.SeedSequence().entropy % 2 ** 63)
        self.rate_hz = rate_hz
        self.seed = int(seed)
        self.noise_std_m = float(noise_std_m)
        if not self.noise_std_m >= 0.0:
            raise ValueError(f'noise_std_m must be >= 0, got {noise_std_m}')
        self.initial_position_m = float(initial_position_m)
        self.parameters = (family_parameters(family, self.seed) if parameters is None
                           else parameters)
        _, plan_rng, noise_rng = _streams(self.seed)
        self._plan_rng, self._noise_rng = plan_rng, noise_rng
        self.gnss_model = gnss_model
        self._receiver = gnss_receiver(gnss_model, receiver, noise_rng)
        self._plan = _Plan(self.parameters)
        # rail_run's first step: standing at a station, a remaining dwell to go.
        self._plan.hold(float(plan_rng.uniform(0.0, self.parameters.dwell_s[1])))
        self._run = None
        self._index = 0

    def run_until(self, t_s: float) -> RailRun:
        """Return the run planned at least up to t_s (the truth at any earlier time)."""
        while self._plan.t_s < t_s:
            _plan_section(self._plan, self._plan_rng)
            self._run = None
        if self._run is None:
            self._run = RailRun(self.parameters, self._plan.phases, self._plan.stops,
                                self.seed)
        return self._run

    def next_sample(self) -> ScenarioSample:
        """Advance one period and return the sample (no control; the true acceleration)."""
        self._index += 1
        t = self._index / self.rate_hz
        # Evaluated as a 1-element array: numpy's array power takes another path than
        # the scalar one (1 ulp apart), and rail_scenario evaluates arrays.
        state = self.run_until(t + PLAN_AHEAD_S).state_at(np.array([t]))
        position = self.initial_position_m + float(state.position_m[0])
        velocity = float(state.velocity_mps[0])
        if self._receiver is None:
            z = position + self.noise_std_m * self._noise_rng.standard_normal()
            return ScenarioSample(self._index, t, position, velocity, float(z), None,
                                  float(state.acceleration_mps2[0]))
        fix = self._receiver.fix(t, position, velocity)
        return ScenarioSample(self._index, t, position, velocity, fix.position_m, None,
                              float(state.acceleration_mps2[0]), _square(fix.h_acc_m),
                              fix.speed_mps, _square(fix.speed_acc_mps))

"""
A jerk-limited rail run: a train that accelerates, cruises, slows, stops and dwells.

The truth is a piecewise-constant jerk profile integrated exactly (cubic position),
so position, velocity, acceleration and jerk are known at any time, not only at the
sample times. A run is a chain of station-to-station sections. In each section the
train

* leaves the station on an S-curve (jerk-limited ramp up to ``accel_mps2``, hold, ramp
  down) to the line speed, or to the highest speed the section allows;
* cruises, coasting now and then (a gentle speed loss of ``coast_drop_mps`` at
  ``coast_mps2``, powered back up), since no driver holds a speed exactly;
* may pass a slow zone: brake to a fraction of the line speed before it, hold that
  speed through it, accelerate back after it;
* brakes on an S-curve (``brake_mps2``) to a stop at the next station and dwells there.

Every speed change is a symmetric S-curve, so its distance is its mean speed times
its duration and the plan is exact: the train never reverses, |a| never exceeds the
limits, |jerk| never exceeds ``jerk_mps3``, and it stands still (v = a = 0) during
each dwell.

:class:`RailParameters` are the values of one run (validated ranges: acceleration
<= 1.3 m/s², braking <= 1.5 m/s², jerk 0.3-1 m/s³, line speed 10-45 m/s); section
lengths, dwell times and slow zones are drawn per section from the ranges it holds.
:data:`FAMILIES` (``metro``, ``regional``) draw the parameters themselves from a
seed, so that each seed is a run no filter was tuned on. One seed gives the whole
run: :func:`rail_run` and :func:`rail_scenario` split it into independent streams
for the parameters, the plan and the measurement noise.
"""

from dataclasses import dataclass, fields
import math
from typing import List, NamedTuple, Optional, Tuple

from kf_train.sim.gnss_receiver import GNSS_MODELS, GnssReceiver, GnssReceiverParameters
from kf_train.sim.scenarios import Scenario
import numpy as np

ACCEL_LIMIT_MPS2 = 1.3
"""Largest tractive acceleration a run may have [m/s²]."""
BRAKE_LIMIT_MPS2 = 1.5
"""Largest service braking a run may have [m/s²]."""
JERK_RANGE_MPS3 = (0.3, 1.0)
"""Jerk limits a run may have [m/s³] (passenger comfort)."""
LINE_SPEED_RANGE_MPS = (10.0, 45.0)
"""Line speeds a run may have [m/s]."""
TEXTURE_ACCEL_MPS2 = (0.05, 0.2)
"""Range of a textured cruise's speed changes [m/s²] (a 0.5-2 % gradient, a notch)."""
STATE_NAMES = ('position', 'velocity', 'acceleration')


def _number(name: str, value, low: float, high: float) -> float:
    """Return ``value`` as a float in [low, high], else raise ValueError naming it."""
    if isinstance(value, bool):
        raise ValueError(f'{name} must be a number, got {value!r}')
    try:
        number = float(value)
    except (TypeError, ValueError):
        raise ValueError(f'{name} must be a number, got {value!r}') from None
    if not low <= number <= high:  # also rejects NaN
        raise ValueError(f'{name} must be in [{low:g}, {high:g}], got {value!r}')
    return number


def _interval(name: str, value, low: float, high: float) -> Tuple[float, float]:
    """Return a (min, max) pair within [low, high] with min <= max."""
    if not isinstance(value, (tuple, list)) or len(value) != 2:
        raise ValueError(f'{name} must be a (min, max) pair, got {value!r}')
    first = _number(f'{name}[0]', value[0], low, high)
    second = _number(f'{name}[1]', value[1], low, high)
    if first > second:
        raise ValueError(f'{name} must have min <= max, got {value!r}')
    return first, second


@dataclass(frozen=True)
class RailParameters:
    """The values of one rail run; ranges are drawn from per section."""

    accel_mps2: float = 1.0
    """Acceleration held on leaving a station (0.05-1.3) [m/s²]."""
    brake_mps2: float = 1.0
    """Service braking (0.05-1.5) [m/s²]."""
    jerk_mps3: float = 0.6
    """Jerk limit of every speed change (0.3-1) [m/s³]."""
    line_speed_mps: float = 20.0
    """Cruising speed between stations (10-45) [m/s]."""
    station_spacing_m: Tuple[float, float] = (800.0, 1500.0)
    """Range of station-to-station distances [m] (>= 100)."""
    dwell_s: Tuple[float, float] = (20.0, 40.0)
    """Range of dwell times at a station [s]."""
    slow_zone_probability: float = 0.3
    """Probability that a section has a slow zone."""
    slow_zone_speed_fraction: Tuple[float, float] = (0.4, 0.7)
    """Range of a slow zone's speed as a fraction of the line speed."""
    slow_zone_length_m: Tuple[float, float] = (100.0, 300.0)
    """Range of a slow zone's length [m]."""
    coast_drop_mps: Tuple[float, float] = (0.0, 1.0)
    """Range of the speed lost while coasting in a cruise [m/s] ((0, 0): none)."""
    coast_mps2: float = 0.05
    """Deceleration while coasting, and acceleration back up [m/s²]."""
    coast_every_s: float = 60.0
    """A cruise coasts once per this many seconds (at least once) [s]."""
    duration_s: float = 600.0
    """Length of the run [s]."""
    texture_speed_mps: float = 0.0
    """Std of a cruise's small speed changes (gradients, traction notches) (0-3) [m/s];
    with it, coasting decelerates at 0.5-1.5 × coast_mps2 (0: none, the old runs)."""
    texture_every_s: float = 20.0
    """A textured cruise changes its speed about once per this many seconds (1-1e6) [s]."""

    def __post_init__(self):
        """Check every value against its range (tuples are normalised to floats)."""
        checks = {
            'accel_mps2': (0.05, ACCEL_LIMIT_MPS2), 'brake_mps2': (0.05, BRAKE_LIMIT_MPS2),
            'jerk_mps3': JERK_RANGE_MPS3, 'line_speed_mps': LINE_SPEED_RANGE_MPS,
            'slow_zone_probability': (0.0, 1.0), 'coast_mps2': (0.01, 0.5),
            'coast_every_s': (1.0, 1e6), 'duration_s': (1.0, 1e6),
            'texture_speed_mps': (0.0, 3.0), 'texture_every_s': (1.0, 1e6)}
        for name, (low, high) in checks.items():
            object.__setattr__(self, name, _number(name, getattr(self, name), low, high))
        intervals = {
            'station_spacing_m': (100.0, 1e6), 'dwell_s': (0.0, 3600.0),
            'slow_zone_speed_fraction': (0.1, 0.95), 'slow_zone_length_m': (0.0, 1e5),
            'coast_drop_mps': (0.0, 5.0)}
        for name, (low, high) in intervals.items():
            object.__setattr__(self, name, _interval(name, getattr(self, name), low, high))


@dataclass(frozen=True)
class RailFamily:
    """Ranges to draw :class:`RailParameters` from: a kind of line, not one run."""

    name: str
    accel_mps2: Tuple[float, float]
    brake_mps2: Tuple[float, float]
    jerk_mps3: Tuple[float, float]
    line_speed_mps: Tuple[float, float]
    fixed: RailParameters
    """Everything not drawn: the per-section ranges, coasting and the duration."""

    def draw(self, rng: np.random.Generator) -> RailParameters:
        """Return parameters drawn uniformly from the family's ranges."""
        drawn = {name: float(rng.uniform(*getattr(self, name)))
                 for name in ('accel_mps2', 'brake_mps2', 'jerk_mps3', 'line_speed_mps')}
        values = {f.name: getattr(self.fixed, f.name) for f in fields(RailParameters)}
        values.update(drawn)
        return RailParameters(**values)


DEFAULT_FAMILY = 'metro'
"""The family a rail run is drawn from when none is named."""

FAMILIES = {
    # Metro: close stations, brisk acceleration and braking, short dwells.
    'metro': RailFamily(
        'metro', accel_mps2=(0.8, 1.3), brake_mps2=(0.8, 1.3), jerk_mps3=(0.5, 1.0),
        line_speed_mps=(15.0, 25.0),
        fixed=RailParameters(station_spacing_m=(600.0, 1500.0), dwell_s=(15.0, 40.0),
                             slow_zone_probability=0.3, slow_zone_length_m=(100.0, 300.0),
                             coast_drop_mps=(0.2, 1.0), coast_mps2=0.05,
                             coast_every_s=40.0, duration_s=600.0)),
    # Regional: stations kilometres apart, gentler, faster, longer dwells.
    'regional': RailFamily(
        'regional', accel_mps2=(0.4, 0.9), brake_mps2=(0.5, 1.1), jerk_mps3=(0.3, 0.7),
        line_speed_mps=(30.0, 45.0),
        fixed=RailParameters(station_spacing_m=(2500.0, 8000.0), dwell_s=(30.0, 90.0),
                             slow_zone_probability=0.5, slow_zone_length_m=(500.0, 1500.0),
                             coast_drop_mps=(0.5, 2.0), coast_mps2=0.05,
                             coast_every_s=60.0, duration_s=900.0)),
}


def s_curve(dv_mps: float, accel_mps2: float, jerk_mps3: float) -> List[Tuple[float, float]]:
    """
    Return the phases (duration [s], jerk [m/s³]) of a jerk-limited speed change dv.

    With |dv| >= a²/j the acceleration ramps to ±a in a/j, holds for |dv|/a - a/j and
    ramps back; below that it peaks at √(|dv|·j) (a triangle). The profile is
    symmetric in time, so its distance is (v0 + v1)/2 times its duration.
    """
    size = abs(dv_mps)
    if size == 0.0:
        return []
    sign = math.copysign(1.0, dv_mps)
    if size >= accel_mps2 ** 2 / jerk_mps3:
        ramp = accel_mps2 / jerk_mps3
        phases = [(ramp, sign * jerk_mps3), (size / accel_mps2 - ramp, 0.0),
                  (ramp, -sign * jerk_mps3)]
        return [phase for phase in phases if phase[0] > 0.0]
    ramp = math.sqrt(size / jerk_mps3)  # peak √(|dv| j) reached after √(|dv|/j)
    return [(ramp, sign * jerk_mps3), (ramp, -sign * jerk_mps3)]


def change_distance_m(v0_mps: float, v1_mps: float, accel_mps2: float,
                      jerk_mps3: float) -> float:
    """Return the distance covered by the S-curve from v0 to v1."""
    duration = sum(d for d, _ in s_curve(v1_mps - v0_mps, accel_mps2, jerk_mps3))
    return 0.5 * (v0_mps + v1_mps) * duration


class _Plan:
    """Phases of constant jerk, appended leg by leg, with the state at each start."""

    def __init__(self, parameters: RailParameters):
        """Start standing at position 0, time 0."""
        self.parameters = parameters
        self.t_s, self.p, self.v, self.a = 0.0, 0.0, 0.0, 0.0
        self.phases: List[Tuple[float, float, float, float, float, float]] = []
        self.stops: List[Tuple[float, float]] = []

    def _phase(self, duration_s: float, jerk: float) -> None:
        """Append one phase and integrate the state exactly to its end."""
        t, p, v, a = duration_s, self.p, self.v, self.a
        self.phases.append((self.t_s, duration_s, p, v, a, jerk))
        self.p = p + v * t + a * t * t / 2.0 + jerk * t ** 3 / 6.0
        self.v = v + a * t + jerk * t * t / 2.0
        self.a = a + jerk * t
        self.t_s += duration_s

    def change(self, v_target: float, accel: float) -> None:
        """Change speed to v_target on an S-curve; snap (v, a) to their planned end."""
        for duration, jerk in s_curve(v_target - self.v, accel, self.parameters.jerk_mps3):
            self._phase(duration, jerk)
        # The end state is v_target with a = 0 exactly; the integration is off by
        # rounding only, which would otherwise leave a standing train at v = -1e-16.
        self.v, self.a = v_target, 0.0

    def hold(self, duration_s: float) -> None:
        """Keep the current speed (a = 0) for duration_s; a stop when standing."""
        if duration_s > 0.0:
            if self.v == 0.0:
                self.stops.append((self.t_s, self.t_s + duration_s))
            self._phase(duration_s, 0.0)

    def cruise(self, distance_m: float, rng: np.random.Generator) -> None:
        """Cruise distance_m at the current speed, coasting now and then."""
        params, speed = self.parameters, self.v
        textured = params.texture_speed_mps > 0.0  # draws nothing more without texture
        count = max(1, int(distance_m / speed // params.coast_every_s))
        piece = distance_m / count
        for _ in range(count):
            drop = min(float(rng.uniform(*params.coast_drop_mps)), 0.5 * speed)
            rate = params.coast_mps2 * (float(rng.uniform(0.5, 1.5)) if textured else 1.0)
            loop = (change_distance_m(speed, speed - drop, rate, params.jerk_mps3)
                    + change_distance_m(speed - drop, speed, rate, params.jerk_mps3))
            if drop <= 0.0 or loop > piece:
                self.steady(piece, rng)
                continue
            before = float(rng.uniform(0.0, piece - loop))
            self.steady(before, rng)
            self.change(speed - drop, rate)
            self.change(speed, rate)
            self.steady(piece - loop - before, rng)

    def steady(self, distance_m: float, rng: np.random.Generator) -> None:
        """
        Cover distance_m at the current speed; textured, with small speed changes.

        Texture: once per ``texture_every_s`` the speed moves by N(0, texture_speed_mps)
        (at most -30 %), holds, and comes back (a gradient, a
        traction notch), so the cruise still ends at its speed and covers distance_m.
        The rate is drawn from TEXTURE_ACCEL_MPS2.
        """
        params, speed = self.parameters, self.v
        if params.texture_speed_mps <= 0.0 or speed <= 0.0:
            self.hold(distance_m / speed)
            return
        count = max(1, int(distance_m / speed // params.texture_every_s))
        piece = distance_m / count
        for _ in range(count):
            delta = max(float(rng.normal(0.0, params.texture_speed_mps)), -0.3 * speed)
            rate = float(rng.uniform(*TEXTURE_ACCEL_MPS2))
            varied = speed + delta
            loop_m = (change_distance_m(speed, varied, rate, params.jerk_mps3)
                      + change_distance_m(varied, speed, rate, params.jerk_mps3))
            if loop_m >= piece:
                self.hold(piece / speed)
                continue
            self.change(varied, rate)
            self.hold((piece - loop_m) / varied)
            self.change(speed, rate)


def _section_speed(params: RailParameters, length_m: float) -> float:
    """Return the line speed, or the highest speed a section of length_m leaves room for."""
    def needed(v):
        return (change_distance_m(0.0, v, params.accel_mps2, params.jerk_mps3)
                + change_distance_m(v, 0.0, params.brake_mps2, params.jerk_mps3))
    room = 0.95 * length_m  # keep a short cruise
    if needed(params.line_speed_mps) <= room:
        return params.line_speed_mps
    low, high = 0.0, params.line_speed_mps
    for _ in range(60):  # bisection: needed(v) increases with v
        middle = 0.5 * (low + high)
        low, high = (middle, high) if needed(middle) <= room else (low, middle)
    return low


def _slow_zone(params: RailParameters, rng: np.random.Generator, length_m: float,
               speed: float) -> Optional[Tuple[float, float, float]]:
    """Return (start m, length m, speed m/s) of a slow zone that fits, or None."""
    if rng.uniform() >= params.slow_zone_probability:
        return None
    zone_speed = speed * float(rng.uniform(*params.slow_zone_speed_fraction))
    zone_length = float(rng.uniform(*params.slow_zone_length_m))
    a, b, j = params.accel_mps2, params.brake_mps2, params.jerk_mps3
    earliest = change_distance_m(0.0, speed, a, j) + change_distance_m(speed, zone_speed, b, j)
    latest = length_m - zone_length - (change_distance_m(zone_speed, speed, a, j)
                                       + change_distance_m(speed, 0.0, b, j))
    if latest <= earliest:
        return None
    return float(rng.uniform(earliest, latest)), zone_length, zone_speed


def _plan_section(plan: _Plan, rng: np.random.Generator) -> None:
    """Append one station-to-station section and the dwell at its end."""
    params = plan.parameters
    a, b, j = params.accel_mps2, params.brake_mps2, params.jerk_mps3
    length = float(rng.uniform(*params.station_spacing_m))
    speed = _section_speed(params, length)
    zone = _slow_zone(params, rng, length, speed)
    start = plan.p
    plan.change(speed, a)
    if zone is not None:
        zone_start, zone_length, zone_speed = zone
        plan.cruise(zone_start - change_distance_m(speed, zone_speed, b, j)
                    - (plan.p - start), rng)
        plan.change(zone_speed, b)
        plan.hold(zone_length / zone_speed)
        plan.change(speed, a)
    remaining = length - (plan.p - start) - change_distance_m(speed, 0.0, b, j)
    plan.cruise(max(remaining, 0.0), rng)
    plan.change(0.0, b)
    plan.hold(float(rng.uniform(*params.dwell_s)))


class RailState(NamedTuple):
    """The true motion at given times."""

    position_m: np.ndarray
    velocity_mps: np.ndarray
    acceleration_mps2: np.ndarray
    jerk_mps3: np.ndarray


class RailRun:
    """The exact truth of one run: phases of constant jerk, and the stops."""

    def __init__(self, parameters: RailParameters, phases, stops, seed: Optional[int]):
        """Keep the phases (start s, duration s, p0, v0, a0, jerk) and stops (from, to)."""
        self.parameters = parameters
        self.seed = seed
        table = np.array(phases, dtype=float).reshape(-1, 6)
        (self.phase_start_s, self.phase_duration_s, self._p0, self._v0, self._a0,
         self._jerk) = table.T
        self.stops = tuple(stops)
        """(arrival s, departure s) of every stop, the initial one included."""
        self.end_s = float(self.phase_start_s[-1] + self.phase_duration_s[-1])
        """The time the plan ends (at least the duration plus the planning margin)."""

    def state_at(self, t_s) -> RailState:
        """Return the true (p, v, a, jerk) at times t_s in [0, end_s]."""
        t = np.asarray(t_s, dtype=float)
        if t.size and not (np.all(np.isfinite(t)) and t.min() >= 0.0
                           and t.max() <= self.end_s):
            raise ValueError(f't_s must be finite and within [0, {self.end_s}] s')
        k = np.clip(np.searchsorted(self.phase_start_s, t, side='right') - 1, 0, None)
        tau = t - self.phase_start_s[k]
        p0, v0, a0, jerk = self._p0[k], self._v0[k], self._a0[k], self._jerk[k]
        position = p0 + v0 * tau + a0 * tau ** 2 / 2.0 + jerk * tau ** 3 / 6.0
        # v >= 0 holds exactly in the plan; a final ramp to a stop may round to -1e-16.
        velocity = np.maximum(v0 + a0 * tau + jerk * tau ** 2 / 2.0, 0.0)
        return RailState(position, velocity, a0 + jerk * tau, jerk.copy())


def _streams(seed: int) -> List[np.random.Generator]:
    """Return independent generators for the parameters, the plan and the noise."""
    if not isinstance(seed, (int, np.integer)) or isinstance(seed, bool) or seed < 0:
        raise ValueError(f'seed must be a non-negative integer, got {seed!r}')
    return [np.random.default_rng(s) for s in np.random.SeedSequence(int(seed)).spawn(3)]


def rail_run(parameters: RailParameters, seed: int = 0, margin_s: float = 10.0) -> RailRun:
    """
    Return the run ``parameters`` and ``seed`` plan, covering duration_s + margin_s.

    It starts standing at a station, with a remaining dwell drawn from [0, max dwell].
    """
    if not isinstance(parameters, RailParameters):
        raise ValueError(f'parameters must be RailParameters, got {type(parameters).__name__}')
    rng = _streams(seed)[1]
    plan = _Plan(parameters)
    plan.hold(float(rng.uniform(0.0, parameters.dwell_s[1])))
    while plan.t_s < parameters.duration_s + _number('margin_s', margin_s, 0.0, 1e6):
        _plan_section(plan, rng)
    return RailRun(parameters, plan.phases, plan.stops, int(seed))


def family_parameters(family: str, seed: int) -> RailParameters:
    """Return the parameters family ``family`` draws for ``seed``."""
    if family not in FAMILIES:
        raise ValueError(f"family must be one of {', '.join(FAMILIES)}, got {family!r}")
    return FAMILIES[family].draw(_streams(seed)[0])


def gnss_receiver(gnss_model: str, receiver: Optional[GnssReceiverParameters],
                  noise_rng: np.random.Generator) -> Optional[GnssReceiver]:
    """Return the receiver of a run measured by ``gnss_model`` ('white': None)."""
    if gnss_model not in GNSS_MODELS:
        raise ValueError(f"gnss_model must be one of {', '.join(GNSS_MODELS)}, "
                         f'got {gnss_model!r}')
    if gnss_model == 'white':
        return None
    return GnssReceiver(GnssReceiverParameters() if receiver is None else receiver, noise_rng)


def rail_scenario(seed: int = 0, family: str = DEFAULT_FAMILY,
                  parameters: Optional[RailParameters] = None, rate_hz: float = 10.0,
                  noise_std_m: float = 1.0, gnss_model: str = 'white',
                  receiver: Optional[GnssReceiverParameters] = None
                  ) -> Tuple[Scenario, RailRun]:
    """
    Return a run sampled as a :class:`~kf_train.sim.scenarios.Scenario`, and the run.

    Without ``parameters`` they are drawn by ``family`` from the seed. Samples are at
    t_k = k / rate_hz (k = 1 .. duration·rate); the truth has [position, velocity,
    acceleration]. ``gnss_model`` 'white' (the default here, the development runs'
    model) measures the position with white noise σ = ``noise_std_m``; 'receiver'
    with :class:`~kf_train.sim.gnss_receiver.GnssReceiver` (``receiver``: its
    parameters, default calibrated), whose epochs without a fix are left out.
    """
    rate_hz = _number('rate_hz', rate_hz, 1e-3, 1e4)
    noise_std_m = _number('noise_std_m', noise_std_m, 0.0, 1e6)
    if parameters is None:
        parameters = family_parameters(family, seed)
    run = rail_run(parameters, seed)
    count = int(math.floor(parameters.duration_s * rate_hz + 1e-9))
    t = np.arange(1, count + 1) / rate_hz
    truth = run.state_at(t)
    noise_rng = _streams(seed)[2]
    receiver_model = gnss_receiver(gnss_model, receiver, noise_rng)
    if receiver_model is None:
        z = truth.position_m + noise_std_m * noise_rng.standard_normal(count)
    else:
        z = np.array([receiver_model.fix(t_k, p_k, v_k).position_m for t_k, p_k, v_k
                      in zip(t, truth.position_m, truth.velocity_mps)], dtype=float)
    rows = np.isfinite(z)  # a receiver's epoch without a fix is no row
    states = np.column_stack(truth[:3])[rows]
    start = run.state_at(0.0)
    scenario = Scenario(f'rail-{family}' if family else 'rail', 0.0, t[rows],
                        z[rows][:, None], None, states,
                        np.array([float(x) for x in start[:3]]), STATE_NAMES, ('position',))
    return scenario, run

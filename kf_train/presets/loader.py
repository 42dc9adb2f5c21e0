"""
Named filter presets: every filter of the seed tutorials as a YAML file.

A preset is everything a filter needs to run, offline or on a stamped stream:
the model (``F(dt)``, ``Q(dt)``, optional ``B(dt)``, the measurement and ``R``), the
initial state and covariance, the nominal sample period, an optional prediction
horizon and the names of the states, measurements and controls. The shipped presets
live in ``kf_train/presets/*.yaml``; a user's own file has the same keys and is
checked the same way, every error naming the key.

Keys of a preset file (``[...]`` = optional):

* ``name``, ``description``, [``seed``], [``notes``]: text.
* ``motion``: ``constant_velocity`` (states [position, velocity]),
  ``constant_velocity_2d`` (states [x, vx, y, vy]), ``random_walk`` (F = I, any
  number of states), or a mapping ``{A: matrix}``. Every motion is
  ``F(dt) = I + dt·A`` with ``A·A = 0`` (exact for these kinematics).
* ``states``: the state names (output columns).
* ``measurements``: the measurement names; CSV column ``z_<name>``.
  [``measurement_aliases``]: ``{name: [other, ...]}`` accepts ``z_<other>`` too.
* [``measurement_model``]: ``linear`` (default; needs ``H`` unless every measurement
  is a state, then H selects them) or ``range_bearing`` (measurements
  [bearing, range]; [``position_states``] default [x, y], [``sensor_position_m``]
  default [0, 0], [``min_range_m``] default 1e-6).
* ``R``: measurement noise, a matrix or the list of its diagonal.
* [``controls``] and ``B``: control names (CSV column ``u``, or ``u_<name>`` when
  there are several) and ``B(dt)``, a matrix whose entries are numbers or
  expressions in ``dt`` (``'dt'``, ``'dt**2/2'``).
* ``process_noise``: one or more of, summed:
  ``per_step`` (a matrix added once per nominal period, as the seeds write
  ``P = F P Fᵀ + Q``), ``continuous`` (a spectral density Qc per second, integrated
  exactly: ``∫ F(s) Qc F(s)ᵀ ds``), ``control_std`` (the controls' noise standard
  deviations, propagated as ``B(dt) diag(std²) B(dt)ᵀ``).
* ``nominal_period_s``: the sample period the seed uses [s].
* ``initial_state``, ``initial_covariance``: the estimate at t0.
* [``horizon_s``]: how far ahead to predict [s]; null or absent for none.
"""

import ast
from dataclasses import dataclass
import os
from typing import Any, Dict, List, Mapping, Optional, Sequence, Tuple, Union

from kf_train.filters import (
    as_covariance, as_duration, as_finite_array, as_matrix, as_vector, ExtendedModel, LinearModel,
    per_step_weights, RangeBearing, white_noise_integrals)
import numpy as np

PRESET_DIR = os.path.dirname(os.path.abspath(__file__))

# The shipped presets, in the order they are listed.
PRESET_NAMES = ('train', 'car', 'car-exact', 'robot', 'robot-exact', 'cv-position',
                'cv-position-velocity', 'range-bearing')

MOTIONS = {
    'constant_velocity': ('position', 'velocity'),
    'constant_velocity_2d': ('x', 'vx', 'y', 'vy'),
}

_KEYS = {
    'name', 'description', 'seed', 'notes', 'motion', 'states', 'measurements',
    'measurement_aliases', 'measurement_model', 'H', 'R', 'position_states',
    'sensor_position_m', 'min_range_m', 'controls', 'B', 'process_noise',
    'nominal_period_s', 'initial_state', 'initial_covariance', 'horizon_s',
}
_NOISE_KEYS = ('per_step', 'continuous', 'control_std')


# ---------------------------------------------------------------------------
# Expressions in dt (entries of B)
# ---------------------------------------------------------------------------

_BINARY = {
    ast.Add: np.add, ast.Sub: np.subtract, ast.Mult: np.multiply,
    ast.Div: np.divide, ast.Pow: np.power,
}


class DtExpression:
    """An arithmetic expression in ``dt``: numbers, ``dt``, + - * / ** and brackets."""

    def __init__(self, text: Union[str, float, int], name: str = 'expression'):
        """Parse ``text`` (or take a number); raise ValueError naming ``name``."""
        if isinstance(text, bool) or not isinstance(text, (str, int, float)):
            raise ValueError(f'{name} must be a number or an expression in dt, got {text!r}')
        self.text = str(text)
        try:
            tree = ast.parse(self.text.strip(), mode='eval')
        except SyntaxError:
            raise ValueError(f'{name}: cannot parse {self.text!r}') from None
        self._check(tree.body, name)
        self._tree = tree.body
        # Evaluate once: a constant is stored as a float, and an expression that
        # fails at dt = 1 (e.g. 1/0) is reported now rather than mid-run.
        value = self(np.array([1.0]))
        if not np.all(np.isfinite(value)):
            raise ValueError(f'{name}: {self.text!r} is not finite at dt = 1')

    def _check(self, node, name: str) -> None:
        """Raise unless ``node`` uses only the allowed syntax."""
        if isinstance(node, ast.BinOp) and type(node.op) in _BINARY:
            self._check(node.left, name)
            self._check(node.right, name)
        elif isinstance(node, ast.UnaryOp) and isinstance(node.op, (ast.UAdd, ast.USub)):
            self._check(node.operand, name)
        elif isinstance(node, ast.Constant) and isinstance(node.value, (int, float)) \
                and not isinstance(node.value, bool):
            pass
        elif isinstance(node, ast.Name) and node.id == 'dt':
            pass
        else:
            raise ValueError(
                f'{name}: {self.text!r} may contain only numbers, dt, + - * / ** '
                'and brackets')

    def _eval(self, node, dt: np.ndarray) -> np.ndarray:
        """Evaluate ``node`` for every dt."""
        if isinstance(node, ast.BinOp):
            return _BINARY[type(node.op)](self._eval(node.left, dt),
                                          self._eval(node.right, dt))
        if isinstance(node, ast.UnaryOp):
            value = self._eval(node.operand, dt)
            return -value if isinstance(node.op, ast.USub) else value
        if isinstance(node, ast.Constant):
            return np.full(dt.shape, float(node.value))
        return dt

    def __call__(self, dt: np.ndarray) -> np.ndarray:
        """Return the expression's value for each entry of ``dt``."""
        dt = np.asarray(dt, dtype=float)
        with np.errstate(all='ignore'):
            return np.broadcast_to(self._eval(self._tree, dt), dt.shape).astype(float)

    def __repr__(self) -> str:
        """Show the text."""
        return f'DtExpression({self.text!r})'


class ControlMatrix:
    """B(dt): an (n, p) matrix of numbers or expressions in dt."""

    def __init__(self, entries, n: int, p: int, name: str = 'B'):
        """Parse an (n, p) nested list (a flat list of n entries when p = 1)."""
        if isinstance(entries, (list, tuple)) and p == 1 and len(entries) == n and \
                all(not isinstance(e, (list, tuple)) for e in entries):
            entries = [[e] for e in entries]
        if not isinstance(entries, (list, tuple)) or len(entries) != n or any(
                not isinstance(row, (list, tuple)) or len(row) != p for row in entries):
            raise ValueError(f'{name} must be a {n}x{p} matrix (one row per state), '
                             f'got {entries!r}')
        self.n, self.p = n, p
        self.entries = [[DtExpression(e, f'{name}[{i}][{j}]') for j, e in enumerate(row)]
                        for i, row in enumerate(entries)]

    def batch(self, dt: np.ndarray) -> np.ndarray:
        """Return B(dt) for every dt: shape (len(dt), n, p)."""
        dt = np.asarray(dt, dtype=float)
        out = np.empty(dt.shape + (self.n, self.p))
        for i, row in enumerate(self.entries):
            for j, expression in enumerate(row):
                out[..., i, j] = expression(dt)
        return out

    def __call__(self, dt: float) -> np.ndarray:
        """Return B(dt) for one dt >= 0."""
        return self.batch(np.array([as_duration('dt', dt)]))[0]

    def __repr__(self) -> str:
        """Show the entries."""
        return f'ControlMatrix({[[e.text for e in row] for row in self.entries]!r})'


# ---------------------------------------------------------------------------
# Dynamics: F(dt) = I + dt·A with A² = 0, and the process noise
# ---------------------------------------------------------------------------

class Dynamics:
    """
    The process model of a preset, vectorised over dt.

    ``F(dt) = I + dt·A``; ``Q(dt)`` sums the configured noise terms; ``B(dt)`` is
    None without control input. Because A² = 0, F(s) Q F(s)ᵀ is a polynomial of
    degree 2 in s, so per-step and continuous noise have closed forms for any dt.
    """

    def __init__(self, A, *, period_s: float, per_step=None, continuous=None,
                 control_std=None, B: Optional[ControlMatrix] = None):
        """Store the model; every matrix is checked against the state dimension."""
        A = as_finite_array('A', A)
        n = A.shape[0] if A.ndim == 2 else 0
        self.A = as_matrix('A', A, n, n)
        if np.max(np.abs(self.A @ self.A), initial=0.0) != 0.0:
            raise ValueError('A must satisfy A·A = 0 (F(dt) = I + dt·A is exact only then)')
        self.n = n
        self.period_s = as_duration('nominal_period_s', period_s)
        if self.period_s == 0.0:
            raise ValueError('nominal_period_s must be > 0')
        self.per_step = None if per_step is None else as_covariance(
            'process_noise.per_step', per_step, n)
        self.continuous = None if continuous is None else as_covariance(
            'process_noise.continuous', continuous, n)
        self.B = B
        self.control_std = None
        if control_std is not None:
            if B is None:
                raise ValueError('process_noise.control_std needs controls and B')
            std = as_vector('process_noise.control_std', control_std, B.p)
            if np.any(std < 0.0):
                raise ValueError(
                    f'process_noise.control_std must be >= 0, got {std.tolist()}')
            self.control_std = std

    @property
    def dim_u(self) -> int:
        """Return the number of controls (0 without control input)."""
        return 0 if self.B is None else self.B.p

    def F_batch(self, dt: np.ndarray) -> np.ndarray:
        """Return F(dt) = I + dt·A for every dt: shape (k, n, n)."""
        dt = np.asarray(dt, dtype=float)
        return np.eye(self.n) + dt[:, None, None] * self.A

    def F_inverse_batch(self, dt: np.ndarray) -> np.ndarray:
        """Return F(dt)⁻¹ = I - dt·A (A² = 0) for every dt."""
        return self.F_batch(-np.asarray(dt, dtype=float))

    def Q_batch(self, dt: np.ndarray) -> np.ndarray:
        """Return Q(dt) for every dt: shape (k, n, n), symmetric to the last bit."""
        dt = np.asarray(dt, dtype=float)
        A = self.A
        Q = np.zeros(dt.shape + (self.n, self.n))
        if self.per_step is not None:
            Qs = self.per_step
            s0, s1, s2 = per_step_weights(dt, self.period_s)
            # Σ w F(s) Qs F(s)ᵀ = S0·Qs + S1·(A Qs + Qs Aᵀ) + S2·A Qs Aᵀ
            Q += (s0[:, None, None] * Qs + s1[:, None, None] * (A @ Qs + Qs @ A.T)
                  + s2[:, None, None] * (A @ Qs @ A.T))
        if self.continuous is not None:
            Qc = self.continuous
            # ∫₀^dt F(s) Qc F(s)ᵀ ds = dt·Qc + dt²/2·(A Qc + Qc Aᵀ) + dt³/3·A Qc Aᵀ
            third, half, one = white_noise_integrals(dt)
            Q += (one[:, None, None] * Qc
                  + half[:, None, None] * (A @ Qc + Qc @ A.T)
                  + third[:, None, None] * (A @ Qc @ A.T))
        if self.control_std is not None:
            Bd = self.B.batch(dt) * self.control_std  # B(dt) diag(std)
            Q += Bd @ np.swapaxes(Bd, -1, -2)         # B diag(std²) Bᵀ
        return 0.5 * (Q + np.swapaxes(Q, -1, -2))

    def B_batch(self, dt: np.ndarray) -> Optional[np.ndarray]:
        """Return B(dt) for every dt (shape (k, n, p)), or None without control."""
        return None if self.B is None else self.B.batch(dt)

    def F(self, dt: float) -> np.ndarray:
        """Return the transition matrix for one dt >= 0."""
        return self.F_batch(np.array([as_duration('dt', dt)]))[0]

    def Q(self, dt: float) -> np.ndarray:
        """Return the process noise for one dt >= 0."""
        return self.Q_batch(np.array([as_duration('dt', dt)]))[0]

    def control(self, dt: float) -> np.ndarray:
        """Return B(dt) for one dt >= 0; raise when there is no control input."""
        if self.B is None:
            raise ValueError('this model has no control input')
        return self.B(dt)


# ---------------------------------------------------------------------------
# The preset
# ---------------------------------------------------------------------------

@dataclass(frozen=True, eq=False)
class Preset:
    """A named, fully specified filter: model, initial estimate, period, horizon."""

    name: str
    description: str
    seed: str
    notes: str
    source: str
    dynamics: Dynamics
    model: Union[LinearModel, ExtendedModel]
    """Has predict(x, P, dt_s, u=None) and update(x, P, z, R=None), as LinearModel."""
    initial_state: np.ndarray
    initial_covariance: np.ndarray
    nominal_period_s: float
    horizon_s: Optional[float]
    measurement_aliases: Mapping[str, Tuple[str, ...]]

    @property
    def linear(self) -> bool:
        """Return whether the measurement model is linear, z = H x."""
        return isinstance(self.model, LinearModel)

    @property
    def state_names(self) -> Tuple[str, ...]:
        """Return the state names, in state order."""
        return self.model.state_names

    @property
    def measurement_names(self) -> Tuple[str, ...]:
        """Return the measurement names, in measurement order."""
        return self.model.measurement_names

    @property
    def control_names(self) -> Tuple[str, ...]:
        """Return the control names (empty without control input)."""
        return self.model.control_names

    @property
    def dim_x(self) -> int:
        """Return the number of states."""
        return len(self.state_names)

    @property
    def dim_z(self) -> int:
        """Return the number of measurement components."""
        return len(self.measurement_names)

    @property
    def dim_u(self) -> int:
        """Return the number of controls."""
        return len(self.control_names)

    def measurement_columns(self) -> Tuple[Tuple[str, ...], ...]:
        """Return, per measurement, the CSV column names accepted for it (z_<name> first)."""
        return tuple(
            tuple('z_' + alias for alias in (name,) + tuple(self.measurement_aliases.get(
                name, ()))) for name in self.measurement_names)

    def control_columns(self) -> Tuple[str, ...]:
        """Return the control CSV columns: 'u' for one control, 'u_<name>' for several."""
        if len(self.control_names) == 1:
            return ('u',)
        return tuple('u_' + name for name in self.control_names)

    def __repr__(self) -> str:
        """Show the name and source."""
        return f'Preset({self.name!r}, source={self.source!r})'


def available_presets() -> List[str]:
    """Return the names of the shipped presets."""
    return list(PRESET_NAMES)


def preset_path(name: str) -> str:
    """Return the YAML file of a shipped preset; raise ValueError for an unknown name."""
    if name not in PRESET_NAMES:
        raise ValueError(f"unknown preset {name!r}; choose one of: {', '.join(PRESET_NAMES)}")
    return os.path.join(PRESET_DIR, name + '.yaml')


def load_preset(name: str) -> Preset:
    """Return a shipped preset by name."""
    return load_preset_file(preset_path(name))


def read_yaml_file(path: str):
    """Return a YAML file's content; one-line ValueError naming the file if unreadable."""
    import yaml
    try:
        with open(path, encoding='utf-8') as stream:
            return yaml.safe_load(stream)
    except OSError as error:
        raise ValueError(f'{path}: cannot read: {error.strerror}') from None
    except yaml.YAMLError as error:
        raise ValueError(f'{path}: not valid YAML: {" ".join(str(error).split())}') from None


def load_preset_file(path: str) -> Preset:
    """Return the preset in a YAML file; every error names the file and the key."""
    return preset_from_mapping(read_yaml_file(path), source=path)


def preset_from_mapping(data: Mapping[str, Any], source: str = '<mapping>') -> Preset:
    """Return the preset a mapping describes (the parsed YAML); errors name the key."""
    try:
        return _build(data, source)
    except ValueError as error:
        raise ValueError(f'{source}: {error}') from None


def _names(data: Mapping, key: str, required: bool = True) -> Tuple[str, ...]:
    """Return a list of distinct, non-empty identifier-like names under ``key``."""
    value = data.get(key)
    if value is None:
        if required:
            raise ValueError(f"'{key}' is required")
        return ()
    if not isinstance(value, (list, tuple)) or not value or any(
            not isinstance(v, str) or not v or any(c in v for c in ', \t\n"') for v in value):
        raise ValueError(f"'{key}' must be a non-empty list of names (no commas, "
                         f'spaces or quotes), got {value!r}')
    if len(set(value)) != len(value):
        raise ValueError(f"'{key}' has repeated names: {value!r}")
    return tuple(value)


def _covariance(key: str, value, dim: int) -> np.ndarray:
    """Return a covariance given as a matrix or as the list of its diagonal."""
    array = as_finite_array(key, value)
    if array.ndim == 1 and array.shape[0] == dim and dim > 1:
        array = np.diag(array)
    return as_covariance(key, array, dim)


def _text(data: Mapping, key: str, default: str = '') -> str:
    """Return the text under ``key``."""
    value = data.get(key, default)
    if value is None:
        return default
    if not isinstance(value, (str, int, float)) or isinstance(value, bool):
        raise ValueError(f"'{key}' must be text, got {value!r}")
    return str(value)


def _number(key: str, value) -> float:
    """Return a finite scalar."""
    array = as_finite_array(key, value)
    if array.ndim != 0 or isinstance(value, bool):
        raise ValueError(f'{key} must be a number, got {value!r}')
    return float(array)


def _motion(value, states: Tuple[str, ...]) -> np.ndarray:
    """Return A for the motion named or given by ``value``."""
    n = len(states)
    if isinstance(value, str):
        if value == 'random_walk':
            return np.zeros((n, n))
        if value not in MOTIONS:
            raise ValueError(
                f"'motion' must be one of {', '.join(sorted(MOTIONS))}, random_walk "
                f'or {{A: matrix}}, got {value!r}')
        if n != len(MOTIONS[value]):
            raise ValueError(
                f"'motion' {value} has {len(MOTIONS[value])} states "
                f'({", ".join(MOTIONS[value])}), but states lists {n}')
        A = np.zeros((n, n))
        for i in range(0, n, 2):
            A[i, i + 1] = 1.0  # d(position)/dt = velocity, per axis
        return A
    if isinstance(value, Mapping) and set(value) == {'A'}:
        return as_matrix('motion.A', value['A'], n, n)
    raise ValueError(f"'motion' must be a name or {{A: matrix}}, got {value!r}")


def check_keys(data, keys) -> None:
    """Raise a ValueError unless ``data`` is a mapping whose keys are all in ``keys``."""
    if not isinstance(data, Mapping):
        raise ValueError(f'a preset must be a mapping of keys, got {type(data).__name__}')
    unknown = sorted(str(k) for k in data if k not in keys)
    if unknown:
        raise ValueError(f"unknown key '{unknown[0]}'; the keys are {', '.join(sorted(keys))}")


def _build(data: Mapping[str, Any], source: str) -> Preset:
    """Validate ``data`` and build the preset; raise ValueError naming the key."""
    check_keys(data, _KEYS)
    name = _text(data, 'name')
    if not name:
        raise ValueError("'name' is required")
    states = _names(data, 'states')
    measurements = _names(data, 'measurements')
    controls = _names(data, 'controls', required=False)
    n, m = len(states), len(measurements)
    if 'motion' not in data:
        raise ValueError("'motion' is required")
    A = _motion(data['motion'], states)
    dynamics, period = _dynamics(data, A, n, len(controls))
    if 'R' not in data:
        raise ValueError("'R' is required")
    R = _covariance('R', data['R'], m)
    if float(np.min(np.linalg.eigvalsh(R))) <= 0.0:
        raise ValueError(f'R must be positive definite, got {R.tolist()}')
    model = _measurement_model(data, dynamics, R, states, measurements, controls)
    aliases = _aliases(data.get('measurement_aliases'), measurements)
    for key in ('initial_state', 'initial_covariance'):
        if key not in data:
            raise ValueError(f"'{key}' is required")
    x0 = as_vector('initial_state', data['initial_state'], n)
    P0 = _covariance('initial_covariance', data['initial_covariance'], n)
    horizon = data.get('horizon_s')
    if horizon is not None:
        horizon = _number('horizon_s', horizon)
        if horizon <= 0.0:
            raise ValueError(f'horizon_s must be > 0 (or null for none), got {horizon}')
    return Preset(name=name, description=_text(data, 'description'),
                  seed=_text(data, 'seed'), notes=_text(data, 'notes'), source=source,
                  dynamics=dynamics, model=model, initial_state=x0, initial_covariance=P0,
                  nominal_period_s=period, horizon_s=horizon,
                  measurement_aliases=aliases)


def _dynamics(data: Mapping[str, Any], A: np.ndarray, n: int, p: int) -> Tuple[Dynamics, float]:
    """Return the preset's Dynamics (B, process noise, period) and its period [s]."""
    if p:
        if 'B' not in data:
            raise ValueError("'B' is required when 'controls' are given")
        B = ControlMatrix(data['B'], n, p, 'B')
    else:
        if data.get('B') is not None:
            raise ValueError("'B' is given but 'controls' is not")
        B = None
    noise = data.get('process_noise')
    if not isinstance(noise, Mapping) or not noise:
        raise ValueError(f"'process_noise' must be a mapping with one or more of "
                         f"{', '.join(_NOISE_KEYS)}, got {noise!r}")
    for key in noise:
        if key not in _NOISE_KEYS:
            raise ValueError(f"unknown key 'process_noise.{key}'; use {', '.join(_NOISE_KEYS)}")
    if 'nominal_period_s' not in data:
        raise ValueError("'nominal_period_s' is required")
    period = _number('nominal_period_s', data['nominal_period_s'])
    if period <= 0.0:
        raise ValueError(f'nominal_period_s must be > 0, got {period}')
    per_step = None if noise.get('per_step') is None else _covariance(
        'process_noise.per_step', noise['per_step'], n)
    continuous = None if noise.get('continuous') is None else _covariance(
        'process_noise.continuous', noise['continuous'], n)
    return Dynamics(A, period_s=period, per_step=per_step, continuous=continuous,
                    control_std=noise.get('control_std'), B=B), period


def _measurement_model(data: Mapping[str, Any], dynamics: Dynamics, R: np.ndarray,
                       states: Tuple[str, ...], measurements: Tuple[str, ...],
                       controls: Tuple[str, ...]):
    """Return the preset's model: linear (H given or selecting states) or range-bearing."""
    n, m = len(states), len(measurements)
    B = dynamics.control if controls else None
    kind = _text(data, 'measurement_model', 'linear')
    if kind == 'linear':
        for key in ('position_states', 'sensor_position_m', 'min_range_m'):
            if key in data:
                raise ValueError(f"'{key}' applies only to measurement_model range_bearing")
        if data.get('H') is None:
            missing = [name for name in measurements if name not in states]
            if missing:
                raise ValueError(f"'H' is required: measurement {missing[0]!r} is not a state")
            H = np.zeros((m, n))
            for i, name in enumerate(measurements):
                H[i, states.index(name)] = 1.0
        else:
            H = as_matrix('H', data['H'], m, n)
        return LinearModel(dynamics.F, dynamics.Q, H, R, B=B, state_names=states,
                           measurement_names=measurements, control_names=controls)
    if kind != 'range_bearing':
        raise ValueError(f"'measurement_model' must be linear or range_bearing, got {kind!r}")
    if 'H' in data:
        raise ValueError("'H' does not apply to measurement_model range_bearing")
    if measurements != ('bearing', 'range'):
        raise ValueError(
            f"'measurements' must be [bearing, range] for range_bearing, got "
            f'{list(measurements)}')
    position_states = _names(data, 'position_states', required=False) or ('x', 'y')
    if len(position_states) != 2 or any(s not in states for s in position_states):
        raise ValueError(f"'position_states' must name two states, got "
                         f'{list(position_states)}')
    sensor = as_vector('sensor_position_m', data.get('sensor_position_m', [0.0, 0.0]), 2)
    min_range = _number('min_range_m', data.get('min_range_m', 1e-6))
    measurement = RangeBearing(dim_x=n, x_index=states.index(position_states[0]),
                               y_index=states.index(position_states[1]),
                               sensor_position_m=sensor, min_range_m=min_range)
    return ExtendedModel(dynamics.F, dynamics.Q, measurement, R, B=B, state_names=states,
                         control_names=controls)


def _aliases(value, measurements: Sequence[str]) -> Dict[str, Tuple[str, ...]]:
    """Return the measurement aliases, checked against the measurement names."""
    if value is None:
        return {}
    if not isinstance(value, Mapping):
        raise ValueError(f"'measurement_aliases' must be a mapping, got {value!r}")
    aliases = {}
    for key, names in value.items():
        if key not in measurements:
            raise ValueError(f"'measurement_aliases' names {key!r}, which is not a measurement")
        aliases[key] = _names({f'measurement_aliases.{key}': names},
                              f'measurement_aliases.{key}')
    return aliases

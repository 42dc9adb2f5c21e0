"""
Node parameters as data: one :class:`ParamSpec` per parameter, checked as ROS checks it.

Pure: no rclpy, no message package. The nodes declare their parameters from these
tables (:mod:`kf_train.ros.parameters` turns a spec into a ParameterDescriptor), and
offline tools read the same tables, so that ``kf-train replay --params-file P -p
NAME:=VALUE`` takes the node's names, defaults and checks, and refuses a value with the
node's own words. What is mirrored from ROS 2 Jazzy, so that a value is refused here
exactly when the node refuses it, with the same one-line text:

* Static types (rclpy ``Parameter.Type.from_parameter_value``): a double parameter
  refuses an integer (``write 10.0``), an array its elements' other type.
* Ranges are inclusive, and a value within rclpy's relative tolerance
  (``Node.PARAM_REL_TOL``, 1e-6) of a double bound counts as on it.
* ``-p NAME:=VALUE`` values and params files are typed by rcl's YAML rules
  (rcl_yaml_param_parser ``get_value``), not PyYAML's: unquoted y/yes/true/on (any of
  their three spellings) are booleans, an integer is what C's ``strtol`` reads whole
  (``0x10`` is 16, ``010`` is 8), a double what ``strtod`` reads whole (``1e3``,
  ``08``, ``.inf``), anything else (quoted, ``null``, ``~``) is a string; a sequence
  must hold one type.
* A params file applies to node ``/NAME`` through its sections ``/**``, ``/*``,
  ``NAME``, ``/NAME``, ``/**/NAME`` (``*`` one name, ``**`` any number), later sections
  over earlier ones, files in the order given, ``-p`` overrides last; nested mappings
  under ``ros__parameters`` name ``outer.inner``.
"""

from dataclasses import dataclass
import difflib
import math
import re
from typing import Any, Callable, Dict, Iterable, Mapping, Optional, Sequence, Tuple, Union

import yaml

BIG = 1e12
"""Largest double range bound advertised; rclpy compares with it inclusively."""
PARAM_REL_TOL = 1e-6
"""rclpy's Node.PARAM_REL_TOL: a double this close (relatively) to a bound is on it."""
IMPLICIT_PARAMETERS = frozenset(('use_sim_time', 'start_type_description_service'))
"""Parameters rclpy declares on every node: accepted in params files, not in a table."""
QOS_OVERRIDES_PREFIX = 'qos_overrides.'
"""rclpy's QoS override parameters (``qos_overrides./TOPIC.subscription.reliability``...),
declared with each publisher and subscription: implicit too."""
MANAGED_DESCRIPTION = (
    'Run as a managed (lifecycle) node: it starts unconfigured, configure declares and '
    'checks the parameters, activate starts it (ros2 lifecycle set; docs/ros.md). Read '
    'from the command line (-p managed:=true) or a params file before the node exists. '
    'Fixed at start-up.')
"""The ``managed`` parameter's description (both nodes: kf_train.ros.lifecycle)."""
TYPES = ('bool', 'integer', 'double', 'string', 'double_array')
"""The parameter types the tables use (ROS: BOOL, INTEGER, DOUBLE, STRING, DOUBLE_ARRAY)."""


def is_implicit(name: str) -> bool:
    """Return whether rclpy declares ``name`` itself (not a table's parameter)."""
    return name in IMPLICIT_PARAMETERS or name.startswith(QOS_OVERRIDES_PREFIX)


class ParameterError(ValueError):
    """
    An invalid parameter value.

    ``str(error)`` is the node's one-line start-up error (printed after ``error: ``,
    exit code 2); ``error.reason`` is what a refused runtime change answers.
    """

    def __init__(self, reason: str, line: Optional[str] = None):
        """Make the error; ``line`` defaults to ``invalid parameter: <reason>``."""
        super().__init__(f'invalid parameter: {reason}' if line is None else line)
        self.reason = reason


@dataclass(frozen=True)
class ParamSpec:
    """One node parameter: everything the node, its docs and offline tools know of it."""

    name: str
    type: str  # noqa: A003 (what it is: one of TYPES)
    default: Any
    """The default (of ``type``); None for a ``derived`` one."""
    description: str
    """What ``ros2 param describe`` shows, and the README and the config file."""
    range: Optional[Tuple[float, float]] = None  # noqa: A003
    """Inclusive [low, high] of an integer or double (the descriptor's range)."""
    choices: Tuple[str, ...] = ()
    """The strings it accepts, if it is one of a list."""
    constraints: str = ''
    """What it accepts, in words, where neither range nor choices say it all."""
    live: bool = True
    """False: read-only, fixed at start-up (restart to change)."""
    unit: str = ''
    group: str = ''
    """The heading it is listed under in the config file."""
    derived: bool = False
    """Its default depends on the table's key parameter (the preset, the scenario)."""

    def __post_init__(self):
        """Check the spec itself: a wrong table is a programming error."""
        if self.type not in TYPES:
            raise ValueError(f'{self.name}: type must be one of {TYPES}, got {self.type!r}')
        if self.range is not None and self.type not in ('integer', 'double'):
            raise ValueError(f'{self.name}: only numbers have a range')
        if self.derived != (self.default is None):
            raise ValueError(f'{self.name}: exactly the derived parameters have no default')
        if not self.derived:
            check_value(self, self.default)
            check_choice(self, self.default)

    @property
    def ros_type(self) -> str:
        """Return the ROS type name: BOOL, INTEGER, DOUBLE, STRING or DOUBLE_ARRAY."""
        return self.type.upper()

    @property
    def additional_constraints(self) -> str:
        """Return the descriptor's additional_constraints text."""
        if self.constraints:
            return self.constraints
        if self.choices:
            return 'one of: ' + ', '.join(self.choices)
        if self.type == 'bool':
            return 'true or false'
        return ''

    @property
    def accepts(self) -> str:
        """Return what it accepts in a few words: its range, or its constraints."""
        if self.range is not None and self.type == 'integer':
            return f'[{self.range[0]}, {self.range[1]}]'
        if self.range is not None:
            return f'[{self.range[0]:g}, {self.range[1]:g}]'
        return self.additional_constraints


# -- one value, as rclpy checks it against its descriptor ----------------------------------

def ros_type_of(value) -> str:
    """Return the ROS type rclpy gives a Python value (Parameter.Type.from_parameter_value)."""
    if value is None:
        return 'NOT_SET'
    for kind, name in ((bool, 'BOOL'), (int, 'INTEGER'), (float, 'DOUBLE'), (str, 'STRING')):
        if isinstance(value, kind):
            return name
    if isinstance(value, (list, tuple)) or type(value).__name__ == 'array':
        for kind, name in ((bool, 'BOOL'), (int, 'INTEGER'), (float, 'DOUBLE'),
                           (str, 'STRING')):
            if value and all(isinstance(v, kind) for v in value):
                return name + '_ARRAY'
        return 'ARRAY' if value else 'EMPTY_ARRAY'
    return type(value).__name__


def wrong_type_line(name: str, value_text: str, want: str, got: str) -> str:
    """Return the start-up line for a value of the wrong type."""
    hint = f' (write {value_text}.0)' if (want, got) == ('DOUBLE', 'INTEGER') else ''
    return f'invalid parameter {name}:={value_text}: must be of type {want}, not {got}{hint}'


def out_of_range_line(name: str, value_text: str, low: str, high: str, integer: bool) -> str:
    """Return the start-up line for a number outside its range (bounds as rclpy prints them)."""
    kind = 'an integer' if integer else 'a double'
    return f'invalid parameter {name}:={value_text}: must be {kind} in [{low}, {high}]'


def check_value(spec: ParamSpec, value):
    """
    Return ``value`` if its type and range suit ``spec``, else raise ParameterError.

    Arrays come back as lists. The texts are rclpy's (reason) and the node's start-up
    line built from rclpy's exception (kf_train.ros.runner).
    """
    got = ros_type_of(value)
    if got == 'EMPTY_ARRAY' and spec.type == 'double_array':
        return []
    if got != spec.ros_type:
        raise ParameterError(
            f"Wrong parameter type, expected 'Type.{spec.ros_type}' got 'Type.{got}'",
            wrong_type_line(spec.name, str(value), spec.ros_type, got))
    if spec.type == 'double_array':
        return list(value)
    if spec.range is None:
        return value
    if spec.type == 'integer':
        low, high = int(spec.range[0]), int(spec.range[1])
        inside = low <= value <= high
    else:
        low, high = float(spec.range[0]), float(spec.range[1])
        inside = (math.isclose(value, low, rel_tol=PARAM_REL_TOL)
                  or math.isclose(value, high, rel_tol=PARAM_REL_TOL) or low < value < high)
    if not inside:
        dot = '.' if spec.type == 'integer' else ''  # (rclpy's two texts differ so)
        raise ParameterError(
            f'Parameter {spec.name} out of range{dot} Min: {low}, Max: {high}, value: {value}',
            out_of_range_line(spec.name, str(value), str(low), str(high),
                              spec.type == 'integer'))
    return value


def check_choice(spec: ParamSpec, value) -> None:
    """Raise ParameterError unless ``value`` is one of the spec's choices (if it has some)."""
    if spec.choices and value not in spec.choices:
        raise ParameterError(
            f"{spec.name} must be one of {', '.join(spec.choices)}, got {value!r}")


# -- a node's table ----------------------------------------------------------------------

@dataclass(frozen=True)
class ParamTable:
    """Every parameter of one node, in declaration order."""

    node: str
    specs: Tuple[ParamSpec, ...]
    key: str = ''
    """The parameter the derived defaults depend on (declared, and checked, first)."""
    derived_defaults: Optional[Callable[[Any], Mapping[str, Any]]] = None
    """key value -> {name: default} of every derived parameter; raises ParameterError."""

    def __post_init__(self):
        """Check the table: unique names, the key first, derived defaults where needed."""
        names = [spec.name for spec in self.specs]
        if len(set(names)) != len(names):
            raise ValueError(f'{self.node}: a parameter is listed twice')
        if self.key and names[0] != self.key:
            raise ValueError(f'{self.node}: the key parameter {self.key} must come first')
        if any(spec.derived for spec in self.specs) and self.derived_defaults is None:
            raise ValueError(f'{self.node}: derived parameters need derived_defaults')

    @property
    def names(self) -> Tuple[str, ...]:
        """Return the parameter names in declaration order."""
        return tuple(spec.name for spec in self.specs)

    def spec(self, name: str) -> ParamSpec:
        """Return the spec of ``name``; raise ParameterError naming the closest ones."""
        for spec in self.specs:
            if spec.name == name:
                return spec
        close = difflib.get_close_matches(name, self.names, n=3)
        hint = f" (did you mean {' or '.join(close)}?)" if close else ''
        raise ParameterError(f'the {self.node} node has no parameter {name!r}{hint}')

    def defaults(self, key_value=None) -> Dict[str, Any]:
        """Return every parameter's default; derived ones for ``key_value`` (None: default)."""
        values = {spec.name: spec.default for spec in self.specs}
        if self.derived_defaults is not None:
            key_spec = self.spec(self.key)
            key_value = key_spec.default if key_value is None else key_value
            check_value(key_spec, key_value)
            check_choice(key_spec, key_value)
            values[self.key] = key_value
            values.update(self.derived_defaults(key_value))
        return values

    def complete(self, values: Mapping[str, Any]) -> Dict[str, Any]:
        """
        Return every parameter's value: ``values`` over the defaults, each checked.

        Checks in the node's order: unknown names, then the key (the derived defaults
        depend on it), then each parameter's type and range in declaration order, then
        the choices. Raises ParameterError with the node's text.
        """
        for name in values:
            if not is_implicit(name):
                self.spec(name)
        defaults = self.defaults(values.get(self.key) if self.key else None)
        result = {spec.name: check_value(spec, values.get(spec.name, defaults[spec.name]))
                  for spec in self.specs}
        for spec in self.specs:
            check_choice(spec, result[spec.name])
        return result

    def changed(self, values: Mapping[str, Any], changes: Mapping[str, Any]) -> Dict[str, Any]:
        """Return ``values`` with ``changes``, refusing read-only ones as rclpy does."""
        changes = {name: value for name, value in changes.items() if not is_implicit(name)}
        for name, value in changes.items():
            spec = self.spec(name)
            if not spec.live and value != values[name]:
                raise ParameterError(f'Trying to set a read-only parameter: {name}.')
        return self.complete({**values, **changes})

    def load(self, params_files: Union[Mapping, Sequence[Mapping]] = (),
             overrides: Iterable[str] = ()) -> Dict[str, Any]:
        """
        Return the values params files and ``-p NAME:=VALUE`` overrides give this node.

        Only what they set: :meth:`complete` adds the defaults and checks everything.
        ``params_files`` is one params-file mapping (ROS format, as
        :func:`read_params_file` returns it) or a sequence of them, applied in order.
        """
        if isinstance(params_files, Mapping):
            params_files = [params_files]
        values = {}
        for params in params_files:
            values.update(node_parameters(params, self.node))
        for assignment in overrides:
            name, value = parse_override(assignment)
            values[name] = value
        return values


# -- rcl's YAML rules ----------------------------------------------------------------------

_TRUE = frozenset('y Y yes Yes YES true True TRUE on On ON'.split())
_FALSE = frozenset('n N no No NO false False FALSE off Off OFF'.split())
_SPACE = r'[ \t\n\v\f\r]*'
# What C's strtol(text, &end, 0) reads whole, and strtod (decimal, hex, inf, nan).
_STRTOL = re.compile(_SPACE + r'[+-]?(0[xX][0-9a-fA-F]+|0[0-7]*|[1-9][0-9]*)')
_STRTOD = re.compile(
    _SPACE + r'[+-]?(?:(?P<dec>(?:[0-9]+\.?[0-9]*|\.[0-9]+)(?:[eE][+-]?[0-9]+)?)'
    r'|(?P<hex>0[xX](?:[0-9a-fA-F]+\.?[0-9a-fA-F]*|\.[0-9a-fA-F]+)(?:[pP][+-]?[0-9]+)?)'
    r'|(?P<inf>inf(?:inity)?)|(?P<nan>nan(?:\([0-9A-Za-z_]*\))?))', re.IGNORECASE)
# rcl's own spellings of YAML's infinities and NaN (any other case is strtod's business).
_YAML_SPECIALS = {
    **{prefix + word: sign * math.inf for prefix, sign in (('.', 1), ('+.', 1), ('-.', -1))
       for word in ('inf', 'Inf', 'INF')},
    **{'.' + word: math.nan for word in ('nan', 'NaN', 'NAN')}}
_INT64 = (-2 ** 63, 2 ** 63 - 1)


def ros_scalar(text: str, quoted: bool = False):
    """Return a YAML scalar typed as rcl types it: bool, int, float, or the text itself."""
    if quoted:
        return text
    if text in _TRUE or text in _FALSE:
        return text in _TRUE
    match = _STRTOL.fullmatch(text)
    if match:
        digits = match.group(1)
        value = int(digits, 16) if digits[:2] in ('0x', '0X') else int(digits, 8 if (
            digits.startswith('0') and len(digits) > 1) else 10)
        value = -value if text.strip().startswith('-') else value
        if _INT64[0] <= value <= _INT64[1]:
            return value
        # strtol's ERANGE: rcl tries it as a double next.
    if text in _YAML_SPECIALS:
        return _YAML_SPECIALS[text]
    match = _STRTOD.fullmatch(text)
    if match:
        body = text.strip()
        if match['hex']:
            value = float.fromhex(body)
        elif match['nan']:
            value = math.nan
        else:
            value = float(body)
        if match['dec'] and (math.isinf(value) or (
                value == 0.0 and re.search(r'[1-9]', body.split('e')[0].split('E')[0]))):
            return text  # strtod's ERANGE (overflow, or underflow to 0): rcl keeps a string
        return value
    return text


def _ros_value(node: yaml.Node, where: str):
    """Return a composed YAML node's value, typed by rcl's rules."""
    if isinstance(node, yaml.ScalarNode):
        if node.value == '' and node.style not in ("'", '"'):
            raise ParameterError(f'{where} has no value')
        return ros_scalar(node.value, quoted=node.style in ("'", '"'))
    if isinstance(node, yaml.SequenceNode):
        items = [_ros_value(item, where) for item in node.value]
        if any(not isinstance(item, (bool, int, float, str)) for item in items):
            raise ParameterError(f'{where} must be a scalar or a sequence of scalars')
        if len({ros_type_of(item) for item in items}) > 1:
            raise ParameterError(f'{where}: a sequence must hold values of one type')
        return items
    return {_ros_value(key, where): _ros_value(value, f'{where}.{key.value}')
            for key, value in node.value}


def parse_value(text: str, name: str = 'the value'):
    """Return a ``-p NAME:=VALUE`` value as ROS types it (a YAML scalar or flow sequence)."""
    try:
        node = yaml.compose(text, Loader=yaml.BaseLoader)
    except yaml.YAMLError as error:
        raise ParameterError(f'{name}: not a YAML value ({" ".join(str(error).split())})')
    if node is None:
        raise ParameterError(f'{name} has no value')
    value = _ros_value(node, name)
    if isinstance(value, dict):
        raise ParameterError(f'{name} must be a scalar or a sequence of scalars')
    return value


def parse_override(assignment: str) -> Tuple[str, Any]:
    """Return (name, value) of one ``NAME:=VALUE`` (as given to ``-p``)."""
    name, separator, text = assignment.partition(':=')
    if not separator or not name:
        raise ParameterError(f'{assignment!r} is not NAME:=VALUE')
    return name, parse_value(text, name)


def read_params_file(source) -> Dict[str, Any]:
    """
    Return a ROS params file as a mapping, every value typed by rcl's rules.

    ``source`` is a path or an open text stream. The result is in params-file form
    (``{'/**': {'ros__parameters': {...}}, ...}``), for :meth:`ParamTable.load`.
    """
    if hasattr(source, 'read'):
        text, where = source.read(), getattr(source, 'name', 'params file')
    else:
        with open(source, encoding='utf-8') as stream:
            text, where = stream.read(), str(source)
    try:
        node = yaml.compose(text, Loader=yaml.BaseLoader)
    except yaml.YAMLError as error:
        raise ParameterError(f'{where} is not YAML: {" ".join(str(error).split())}') from None
    if node is None:
        return {}
    if not isinstance(node, yaml.MappingNode):
        raise ParameterError(f'{where} must map node names to ros__parameters')
    return _ros_value(node, where)


def node_parameters(params: Mapping, node: str, namespace: str = '/') -> Dict[str, Any]:
    """
    Return the parameters a params-file mapping gives node ``namespace/node``.

    Sections apply in file order, later over earlier; a section name may nest (``ns:
    node: ros__parameters:``) and use ``*`` / ``**`` wildcards.
    """
    fqn = [token for token in (namespace.strip('/').split('/') + [node]) if token]
    values: Dict[str, Any] = {}
    for path, parameters in _sections(params, ()):
        pattern = [token for token in '/'.join(path).split('/') if token]
        if _matches(pattern, fqn):
            values.update(_flatten(parameters, ''))
    return values


def _sections(mapping: Mapping, path: Tuple[str, ...]):
    """Yield (section name tokens, ros__parameters mapping) in file order."""
    for key, value in mapping.items():
        if not isinstance(value, Mapping):
            raise ParameterError(f"params file: {'/'.join(path + (str(key),))} must be a "
                                 'mapping (node name: ros__parameters: ...)')
        if key == 'ros__parameters':
            yield path, value
        else:
            yield from _sections(value, path + (str(key),))


def _matches(pattern: Sequence[str], fqn: Sequence[str]) -> bool:
    """Return whether a section name's tokens match a node's (``*`` one, ``**`` any)."""
    if not pattern:
        return not fqn
    if pattern[0] == '**':
        return any(_matches(pattern[1:], fqn[i:]) for i in range(len(fqn) + 1))
    return bool(fqn) and pattern[0] in ('*', fqn[0]) and _matches(pattern[1:], fqn[1:])


def _flatten(parameters: Mapping, prefix: str) -> Dict[str, Any]:
    """Return nested parameter mappings as {'outer.inner': value}."""
    flat = {}
    for key, value in parameters.items():
        if isinstance(value, Mapping):
            flat.update(_flatten(value, f'{prefix}{key}.'))
        else:
            flat[f'{prefix}{key}'] = value
    return flat


def yaml_scalar(value) -> str:
    """Return a value as a YAML literal that rcl and PyYAML both read back as itself."""
    if isinstance(value, bool):
        return 'true' if value else 'false'
    if isinstance(value, float):
        if math.isnan(value):
            return '.nan'
        if math.isinf(value):
            return '.inf' if value > 0 else '-.inf'
        text = repr(value)
        # PyYAML (YAML 1.1) wants a dot and a signed exponent: 1e-06 -> 1.0e-06.
        if 'e' in text and '.' not in text:
            text = text.replace('e', '.0e')
        return text  # (repr signs every exponent)
    if isinstance(value, int):
        return str(value)
    if isinstance(value, str):
        if re.fullmatch(r'[A-Za-z_/][A-Za-z0-9_./-]*', value) and ros_scalar(value) == value \
                and yaml.safe_load(value) == value:
            return value
        return "'" + value.replace("'", "''") + "'"
    if isinstance(value, (list, tuple)):
        return '[' + ', '.join(yaml_scalar(v) for v in value) + ']'
    raise TypeError(f'no YAML form for {value!r}')

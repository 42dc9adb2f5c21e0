"""
Parameters of the launch files' nodes, from a ROS params file and the launch arguments.

The launch files (``launch/*.launch.py``) read the params file themselves (with the
parameter tables' reader, so values are typed as rcl types them) rather than hand it
to the nodes with ``--params-file``, for two reasons:

* Namespaces. In a params file, rcl matches the key ``estimator`` to the node
  ``/estimator`` only, so ``namespace:=/train1`` would silently drop the whole file.
  Here a section applies if it matches the node without the namespace (``/**``,
  ``estimator``, ``/**/estimator``, ...) or in it (``/train1/estimator``,
  ``/train1/*``, ...); sections apply in file order, later over earlier, as in rcl.
* Preset- and scenario-dependent values. The parameters whose defaults derive from
  the preset (estimator) or the scenario (simulator) are marked ``derived`` in the
  tables (kf_train/ros/estimator_params.py, simulator_params.py). A params file that
  lists them, as the installed config/kf_train.yaml does with the train's values, made
  them for the preset or scenario it names (the default when it names none). When a
  launch argument chooses another one, those values are left out so that the chosen
  one's own defaults apply; ``initial_state: [0.0, 5.0]`` would otherwise stop the
  one-state robot preset at start-up.

No launch or rclpy import: plain data handling, tested on its own.
"""

from typing import Dict, Optional

from kf_train.ros import estimator_params, simulator_params
from kf_train.ros.param_spec import node_parameters as matching_sections
from kf_train.ros.param_spec import ParameterError, ParamTable, read_params_file

TRUE_WORDS = ('true', 'yes', 'on', '1')
FALSE_WORDS = ('false', 'no', 'off', '0')


def load_params_file(path: str) -> dict:
    """Return a ROS params file as a mapping; a missing or bad one raises ValueError."""
    try:
        return read_params_file(path)
    except FileNotFoundError:
        raise ValueError(f'params file {path!r} does not exist') from None
    except (OSError, UnicodeDecodeError) as error:
        raise ValueError(f'params file {path!r} cannot be read: {error}') from None
    except ParameterError as error:
        raise ValueError(f'params file {path!r}: {error.reason}') from None


def node_parameters(params: dict, name: str, namespace: str = '') -> Dict[str, object]:
    """Return what the params file gives node ``name`` launched in ``namespace``."""
    values: Dict[str, object] = {}
    try:
        # Section by section in file order (later wins, as in rcl); each one applies if
        # it matches the node with its namespace or without.
        for key, section in params.items():
            values.update(matching_sections({key: section}, name, '/'))
            if namespace.strip('/'):
                values.update(matching_sections({key: section}, name, namespace))
    except ParameterError as error:
        raise ValueError(f'params file: {error.reason}') from None
    return values


def choose(table: ParamTable, parameters: Dict[str, object],
           value: Optional[str]) -> Dict[str, object]:
    """
    Return ``parameters`` with the table's key (preset, scenario) set to ``value``.

    An empty ``value`` changes nothing. When ``value`` differs from the file's choice
    (its value of the key, else the key's default), the derived parameters, whose
    values were made for the file's choice, are left out.
    """
    result = dict(parameters)
    if not value:
        return result
    if value != result.get(table.key, table.spec(table.key).default):
        for spec in table.specs:
            if spec.derived:
                result.pop(spec.name, None)
    result[table.key] = value
    return result


def parse_bool(name: str, text: str) -> bool:
    """Return a launch argument's text as a bool; anything else raises ValueError."""
    word = str(text).strip().lower()
    if word in TRUE_WORDS:
        return True
    if word in FALSE_WORDS:
        return False
    raise ValueError(f'launch argument {name}:={text!r} must be true or false')


def with_managed(values: Dict[str, object], text: str) -> Dict[str, object]:
    """Return a node's ``values`` with the launch argument ``managed`` ('': the file's)."""
    if str(text).strip():
        values = dict(values, managed=parse_bool('managed', text))
    return values


def simulator_parameters(params: dict, namespace: str, scenario: str,
                         use_sim_time: bool) -> Dict[str, object]:
    """Return the simulator's parameters: its file sections, the scenario, use_sim_time."""
    table = simulator_params.PARAMETERS
    values = choose(table, node_parameters(params, table.node, namespace), scenario)
    values['use_sim_time'] = use_sim_time
    return values


def estimator_parameters(params: dict, namespace: str, preset: str,
                         use_sim_time: bool) -> Dict[str, object]:
    """Return the estimator's parameters: its file sections, the preset, use_sim_time."""
    table = estimator_params.PARAMETERS
    values = choose(table, node_parameters(params, table.node, namespace), preset)
    values['use_sim_time'] = use_sim_time
    return values

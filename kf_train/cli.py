"""
The ``kf-train`` umbrella command: ``kf-train <command> [arguments]``.

Each command lives in its own module with a ``main(argv) -> int``; modules are
imported only when their command runs, so that starting a node never pays for
plotting or benchmarking imports.
"""

import importlib
import sys
from typing import List, Optional

# command -> (module with main(argv) -> int, one-line help)
COMMANDS = {
    'simulator': ('kf_train.simulator_node', 'run the simulator node (ROS arguments follow)'),
    'estimator': ('kf_train.estimator_node', 'run the estimator node (ROS arguments follow)'),
    'demo': ('kf_train.demo', 'run seed 000 over DDS with both nodes and print a report'),
    'replay': ('kf_train.replay', 'run a preset filter over a CSV of measurements, offline'),
    'plot': ('kf_train.plotting', "write PNG figures: the seeds' scenarios or a replay"),
    'compare': ('kf_train.compare', 'compare KF/EKF, UKF and particle filter by Monte Carlo'),
    'bench': ('kf_train.bench', 'measure performance side by side, print one table'),
}


def usage() -> str:
    """Return the help text listing every command."""
    width = max(len(name) for name in COMMANDS)
    lines = ['usage: kf-train <command> [arguments]', '', 'commands:']
    lines += [f'  {name:<{width}}  {text}' for name, (_, text) in COMMANDS.items()]
    lines += ['', "Run 'kf-train <command> --help' for a command's own options."]
    return '\n'.join(lines)


def main(argv: Optional[List[str]] = None) -> int:
    """Dispatch to a command; return its exit code."""
    argv = sys.argv[1:] if argv is None else list(argv)
    if not argv or argv[0] in ('-h', '--help', 'help'):
        print(usage())
        return 0
    name, rest = argv[0], argv[1:]
    if name not in COMMANDS:
        print(f"kf-train: unknown command '{name}'\n\n{usage()}", file=sys.stderr)
        return 2
    module = importlib.import_module(COMMANDS[name][0])
    if name in ('simulator', 'estimator'):
        # rclpy parses --ros-args from an argv whose first entry is the program.
        return module.main([f'kf-train {name}'] + rest)
    return module.main(rest)


if __name__ == '__main__':
    sys.exit(main())

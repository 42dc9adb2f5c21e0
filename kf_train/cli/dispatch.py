"""
The ``kf-train`` umbrella command: ``kf-train <command> [arguments]``.

Each command lives in its own module with a ``main(argv) -> int``; modules are
imported only when their command runs, so that starting a node never pays for
plotting or benchmarking imports. ``bench`` is the exception: the benchmark is not
part of the installed package (it imports filterpy, a test and benchmark oracle), so
``kf-train bench`` runs ``benchmarks/bench.py`` of the source tree this package was
installed from (editable or ``colcon build --symlink-install``), or says where it is
missing.
"""

import importlib
import importlib.util
import os
import sys
from typing import List, Optional

# command -> (module with main(argv) -> int, one-line help)
COMMANDS = {
    'simulator': ('kf_train.ros.simulator_node', 'run the simulator node (ROS arguments follow)'),
    'estimator': ('kf_train.ros.estimator_node', 'run the estimator node (ROS arguments follow)'),
    'demo': ('kf_train.cli.demo', 'run seed 000 over DDS with both nodes and print a report'),
    'replay': ('kf_train.cli.replay', 'run a filter over a CSV, Parquet or rosbag2 bag, offline'),
    'simulate': ('kf_train.cli.simulate', 'write a simulated run to a bag or CSV, no DDS'),
    'plot': ('kf_train.cli.plotting', "write PNG figures: the seeds' scenarios or a replay"),
    'compare': ('kf_train.cli.compare', 'compare KF/EKF, UKF and particle filter by Monte Carlo'),
    'tune': ('kf_train.cli.tune', 'estimate q and R from measurements, write a params file'),
    'bench': (None, 'measure performance side by side, print one table'),
}


def usage() -> str:
    """Return the help text listing every command."""
    width = max(len(name) for name in COMMANDS)
    lines = ['usage: kf-train <command> [arguments]', '', 'commands:']
    lines += [f'  {name:<{width}}  {text}' for name, (_, text) in COMMANDS.items()]
    lines += ['', "Run 'kf-train <command> --help' for a command's own options."]
    return '\n'.join(lines)


def bench_script() -> str:
    """Return the path of ``benchmarks/bench.py`` beside this package's source tree."""
    package = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    return os.path.join(os.path.dirname(package), 'benchmarks', 'bench.py')


def _run_bench(argv: List[str]) -> int:
    """Run the benchmark script of the source tree; exit 2 if there is none."""
    script = bench_script()
    if not os.path.isfile(script):
        print(f'kf-train bench: {script} not found: the benchmark is not installed; '
              'run make bench in a source checkout', file=sys.stderr)
        return 2
    spec = importlib.util.spec_from_file_location('kf_train_bench', script)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module.main(argv)


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
    if name == 'bench':
        return _run_bench(rest)
    module = importlib.import_module(COMMANDS[name][0])
    if name in ('simulator', 'estimator'):
        # rclpy parses --ros-args from an argv whose first entry is the program.
        return module.main([f'kf-train {name}'] + rest)
    return module.main(rest)


if __name__ == '__main__':
    sys.exit(main())

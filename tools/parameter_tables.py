"""
Print, check or write the documents generated from the nodes' parameter tables.

    python tools/parameter_tables.py            # print docs/ros.md's parameter tables
    python tools/parameter_tables.py --config   # print config/kf_train.yaml
    python tools/parameter_tables.py --write    # write both into docs/ros.md and config/
    python tools/parameter_tables.py --check    # exit 1 if either file differs

The tables are kf_train/ros/simulator_params.py and kf_train/ros/estimator_params.py;
test/unit/test_param_tables.py keeps docs/ros.md and config/kf_train.yaml equal to them.
"""

import os
import sys

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, REPO)

from kf_train.ros import estimator_params, simulator_params  # noqa: E402
from kf_train.ros.param_docs import CONFIG_HEADER, params_file, reference_tables  # noqa: E402

TABLES = (simulator_params.PARAMETERS, estimator_params.PARAMETERS)
REFERENCE = os.path.join(REPO, 'docs', 'ros.md')
CONFIG = os.path.join(REPO, 'config', 'kf_train.yaml')
# The tables sit between the first node's heading and the next section (or the end).
START = '### `simulator`\n'
END = '\n## '


def config_text() -> str:
    """Return config/kf_train.yaml as the tables make it."""
    return params_file([(table, None) for table in TABLES], CONFIG_HEADER)


def reference_text(current: str) -> str:
    """Return ``current`` docs/ros.md text with its parameter tables regenerated."""
    start = current.index(START)
    end = current.find(END, start)
    end = len(current) if end < 0 else end
    return current[:start] + reference_tables(TABLES) + current[end:]


def _read(path: str) -> str:
    """Return a file's text."""
    with open(path, encoding='utf-8') as stream:
        return stream.read()


def main(argv) -> int:
    """Print, write or check; return the exit code."""
    if argv[1:] == ['--config']:
        sys.stdout.write(config_text())
    elif argv[1:] in (['--write'], ['--check']):
        wanted = {REFERENCE: reference_text(_read(REFERENCE)), CONFIG: config_text()}
        stale = [path for path, text in wanted.items() if _read(path) != text]
        if argv[1] == '--check':
            for path in stale:
                print(f'{os.path.relpath(path, REPO)} differs from the parameter tables',
                      file=sys.stderr)
            return 1 if stale else 0
        for path in stale:
            with open(path, 'w', encoding='utf-8') as stream:
                stream.write(wanted[path])
            print(f'wrote {os.path.relpath(path, REPO)}')
    elif len(argv) == 1:
        sys.stdout.write(reference_tables(TABLES))
    else:
        print(__doc__, file=sys.stderr)
        return 2
    return 0


if __name__ == '__main__':
    sys.exit(main(sys.argv))

r"""
The real-log benchmark over variants of the rail preset: which change helps where.

Each variant is a set of overrides of the rail preset's ``parameters`` (the keys of
kf_train/presets/rail.yaml). For each, benchmarks/real_logs.py replays every tp-lib
log through the node's defaults with that preset (``-p preset:=FILE``) and the script
prints, per log, the 2-s RMSE and its ratio to the better hindsight-tuned CV or CA, and
the geometric mean of the ratios over the clean logs and over the others. The default
preset is always the first row, so each sweep's figures are read against it in one run.

    PYTHONPATH=. python benchmarks/real_logs_sweep.py \
        --variant 'floor=noise_scale_min:1.0e-5' \
        --variant 'fast=noise_window:20,noise_scale_min:1.0e-5' [--logs 28876,31176]

A log's RMSE can hinge on one event (a lock-out, a reacquisition): read the per-log
ratios, not the means alone. Figures only, no assertion.
"""

import argparse
import json
import math
import os
from pathlib import Path
import subprocess
import sys
import tempfile
from typing import Dict, List

import yaml

HERE = Path(__file__).resolve().parent
RAIL_YAML = HERE.parent / 'kf_train' / 'presets' / 'rail.yaml'


def parse_variant(text: str) -> tuple:
    """Return (name, {parameter: value}) of ``NAME=KEY:VALUE,KEY:VALUE``."""
    name, _, body = text.partition('=')
    overrides = {}
    for item in filter(None, body.split(',')):
        key, _, value = item.partition(':')
        if not key or not value:
            raise ValueError(f'a variant is NAME=KEY:VALUE,...; got {text!r}')
        overrides[key.strip()] = yaml.safe_load(value)
    if not name:
        raise ValueError(f'a variant needs a name: {text!r}')
    return name, overrides


def write_preset(overrides: Dict[str, object], path: Path) -> None:
    """Write the rail preset with ``overrides`` in its parameters to ``path``."""
    preset = yaml.safe_load(RAIL_YAML.read_text())
    unknown = set(overrides) - set(preset['parameters'])
    if unknown:
        raise ValueError(f'not rail preset parameters: {sorted(unknown)}')
    preset['parameters'].update(overrides)
    path.write_text(yaml.safe_dump(preset, sort_keys=False))


def run_variant(preset: Path, out: Path, passed: List[str]) -> List[dict]:
    """Run benchmarks/real_logs.py with ``preset``; return its JSON figures."""
    command = [sys.executable, str(HERE / 'real_logs.py'), '--json', str(out),
               '-p', f'preset:={preset}'] + passed
    subprocess.run(command, check=True, stdout=subprocess.DEVNULL, env=os.environ.copy())
    return json.loads(out.read_text())


def summary(name: str, results: List[dict]) -> str:
    """Return one line: the geometric means per class and each log's RMSE / ratio."""
    ratios: Dict[bool, List[float]] = {True: [], False: []}
    cells = []
    for result in results:
        best = min(result['CV']['rmse_m'], result['CA']['rmse_m'])
        rmse = result['default']['rmse_m']
        ratios[result['artefacts']['class'] == 'clean'].append(rmse / best)
        cells.append(f"{result['name'].removeprefix('log_')} {rmse:.2f}/{rmse / best:.2f}")

    def mean(values: List[float]) -> str:
        return f'{math.exp(sum(map(math.log, values)) / len(values)):.2f}' if values else '-'
    return (f'{name}: clean {mean(ratios[True])}, others {mean(ratios[False])} | '
            + ' '.join(cells))


def main() -> int:
    """Run the default and every variant; print one line each."""
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[1])
    parser.add_argument('--variant', action='append', default=[], metavar='NAME=KEY:VALUE,...',
                        help='overrides of the rail preset parameters; may be repeated')
    parser.add_argument('--logs', help='comma-separated log ids (default: all)')
    parser.add_argument('--data', help="tp-lib's test-data, as real_logs.py's --data")
    parser.add_argument('--cache', help="the cache, as real_logs.py's --cache")
    args = parser.parse_args()
    passed = [f'--{key}={value}' for key, value in
              (('logs', args.logs), ('data', args.data), ('cache', args.cache)) if value]
    variants = [('default', {})] + [parse_variant(text) for text in args.variant]
    print('per log: 2-s RMSE [m] / ratio to the better hindsight-tuned CV or CA; '
          'geometric means of the ratios', flush=True)
    with tempfile.TemporaryDirectory() as directory:
        for name, overrides in variants:
            preset = Path(directory) / f'{name}.yaml'
            write_preset(overrides, preset)
            results = run_variant(preset, Path(directory) / f'{name}.json', passed)
            print(summary(name, results), flush=True)
    return 0


if __name__ == '__main__':
    sys.exit(main())

"""
``kf-train tune`` on real recordings: tuned on one log, judged on another (issue 20).

tp-lib's GNSS logs of Belgian trains (Apache-2.0; not in this repository:
benchmarks/real_logs.py says how to get them and caches each as an along-track series
and a bag, R = 3 m² per fix). For every log A in the list, with B the next log (a
ring), this script

1. tunes the rail preset on A's bag, as a user would: ``kf-train tune A.mcap -o
   PARAMS.yaml`` (the node's defaults as the start, the built-in hold-out on);
2. replays B's bag through the node's session twice, with the defaults and with
   PARAMS.yaml (``kf-train replay B.mcap --params-file``), and scores the 2-s prediction
   against the fix 2 s later (benchmarks/real_logs.py's scoring, from 10 s on);
3. prints one row per pair: the tuned noises, the lag-1 autocorrelation of A's
   innovations (start → tuned), the fit's time, whether tune kept the defaults or
   refused (held-out worse), the RMSE on B before and after, and whether the tuned file
   made B worse (the target: never).

``--starts`` also tunes the first ``--starts`` logs from three starts (the defaults,
the defaults' noises ×100 and /100 as a --config preset file) and prints whether
the three answers agree to the printed digits (the target: they do).

    PYTHONPATH=. python benchmarks/tune_real_logs.py [--logs 28876,...] [--starts N]

Figures only, no assertion.
"""

import argparse
import contextlib
import io
from pathlib import Path
import re
import sys
import tempfile
import time
from typing import Dict, List, Tuple

sys.path.insert(0, str(Path(__file__).resolve().parent))

from kf_train.cli import tune as tune_cli  # noqa: E402
from kf_train.sim.rail_eval import format_table  # noqa: E402
import real_logs  # noqa: E402
import yaml  # noqa: E402

ESTIMATE = re.compile(r'^\s+(q_a|q_l|q_c|R)\s+\S+\s+\[[^\]]*\]\s+(\S+)', re.MULTILINE)
LAG1 = re.compile(r'^lag-1 autocorrelation .*: before (\S+), after (\S+)$', re.MULTILINE)


def tune(bag: Path, output: Path, extra: List[str] = ()) -> Tuple[int, str, float]:
    """Run ``kf-train tune BAG -o OUTPUT``; return (exit code, its report, seconds)."""
    out, err = io.StringIO(), io.StringIO()
    began = time.perf_counter()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = tune_cli.main([str(bag), '-o', str(output), *extra])
    return code, out.getvalue() + err.getvalue(), time.perf_counter() - began


def estimates(report: str) -> Dict[str, str]:
    """Return {symbol: printed estimate} from tune's table."""
    return {m.group(1): m.group(2) for m in ESTIMATE.finditer(report)}


def judged(series, facts, bag: Path, params: List[str]) -> Tuple[float, float, dict]:
    """Return (2-s RMSE, 2σ coverage, resets) of the node's replay of ``bag``."""
    run = real_logs.replay_default(series, facts, bag, params)
    rmse, coverage, _ = real_logs.score(series['t_s'], series['x_m'], run['mean'],
                                        run['variance'], run['r_m2'])
    return rmse, coverage, run['resets']


def start_files(directory: Path) -> List[Tuple[str, List[str]]]:
    """Return the three starts: the defaults, and preset files with the noises ×100, /100."""
    from kf_train.presets import load_rail_preset
    source = load_rail_preset().source
    data = yaml.safe_load(Path(source).read_text(encoding='utf-8'))
    starts = [('defaults', [])]
    for label, factor in (('×100', 100.0), ('/100', 0.01)):
        changed = dict(data, parameters=dict(data['parameters']))
        for name in ('acceleration_noise', 'command_noise'):
            changed['parameters'][name] = float(data['parameters'][name]) * factor
        path = directory / f'start{factor:g}.yaml'
        path.write_text(yaml.safe_dump(changed, sort_keys=False, allow_unicode=True))
        starts.append((label, ['--config', str(path)]))
    return starts


def main() -> int:
    """Run the pairs (and the starts); print the tables."""
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[1])
    parser.add_argument('--cache', default=str(real_logs.DEFAULT_CACHE))
    parser.add_argument('--logs', help='comma-separated log ids (default: all)')
    parser.add_argument('--starts', type=int, default=0, metavar='N',
                        help='also tune the first N logs from three starts')
    args = parser.parse_args()
    cache = Path(args.cache).expanduser()
    logs = real_logs.find_logs(cache / 'test-data')
    if args.logs:
        wanted = {w if w.startswith('log_') else f'log_{w}' for w in args.logs.split(',')}
        logs = {k: v for k, v in logs.items() if k in wanted}
    names = sorted(logs)
    data = {n: real_logs.load_series(n, logs[n], cache) for n in names}
    bags = {n: cache / 'bags' / f'{n}.mcap' for n in names}
    rows, agree = [], []
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        for n in names:
            real_logs.write_bag(*data[n], bags[n])
        for k, a in enumerate(names):
            b = names[(k + 1) % len(names)]
            params = work / f'{a}.yaml'
            code, report, seconds = tune(bags[a], params)
            written = params.exists()
            found = estimates(report)
            lag1 = LAG1.search(report)
            before = judged(*data[b], bags[b], [])
            after = judged(*data[b], bags[b], [str(params)]) if written else before
            verdict = 'no file' if not written else (
                'worse' if after[0] > before[0] else 'not worse')
            rows.append((a, b, found.get('q_a', '-'), found.get('q_l', '-'),
                         f'{lag1.group(1)} → {lag1.group(2)}' if lag1 else '-', f'{seconds:.1f}',
                         'written' if written else f'not written (exit {code})',
                         f'{before[0]:.3f}', f'{after[0]:.3f}',
                         f'{100 * before[1]:.1f} → {100 * after[1]:.1f} %', verdict))
            print(f'{a} -> {b}: {rows[-1]}', flush=True)
            if k < args.starts:
                answers = []
                for label, extra in start_files(work):
                    out = work / f'{a}-{len(answers)}.yaml'
                    answers.append((label, estimates(tune(bags[a], out, extra)[1])))
                same = all(x[1] == answers[0][1] for x in answers)
                cells = [f'{label}: {values}' for label, values in answers]
                agree.append((a, *cells, 'yes' if same else 'NO'))
    print('\nTuned on A (kf-train tune A.mcap, defaults as the start), replayed on B; '
          '2-s RMSE [m] against the fix 2 s later\n')
    print(format_table(('A', 'B', 'q_a', 'q_l', 'lag-1 on A', 'tune [s]', 'params file',
                        'B defaults', 'B tuned', 'B 2σ coverage', 'B'), rows))
    if agree:
        print('\nThree starts (the defaults, noises ×100, /100): the same answer?\n')
        print(format_table(('log', 'defaults', '×100', '/100', 'same'), agree))
    return 0


if __name__ == '__main__':
    sys.exit(main())

"""
``make bench`` row 11: ``kf-train tune`` on the node's default model, as a user runs it.

A rail bag of the realistic receiver model (``kf-train simulate --scenario rail``: the
time-correlated GNSS error, its reported variances, dropped epochs) of 30,000 fixes at
10 Hz (3,000 with ``--quick``) is tuned by ``kf-train tune BAG -o PARAMS.yaml``, the
defaults as the start and the hold-out on, in a child process (import and start-up
included). The row reports the fit's time (the maximum-likelihood climb over the node's
likelihood, numba when installed) and the whole command's (reading the bag, the fit,
the node's two runs that score the held-out end, its rail IMM compiled when numba is
installed, without KF_TRAIN_JIT: :mod:`kf_train.tune.validation`), against issue 20's
target: a 30,000-fix rail log tuned in <= 30 s; and the fit's passes and stop.
"""

import os
import re
import subprocess
import sys
import tempfile
import time
from typing import List

from bench_common import Row, verdict

TARGET_S = 30.0
FIT = re.compile(r'(\d+) passes over the data \((\d+) settings\), ([\d.]+) s; stopped: (.*)$',
                 re.MULTILINE)


def rows_tune(quick: bool) -> List[Row]:
    """Return row 11: the rail tune's fit and command times on a simulated bag."""
    fixes = 3_000 if quick else 30_000
    with tempfile.TemporaryDirectory() as directory:
        bag = os.path.join(directory, 'run.mcap')
        simulate = [sys.executable, '-m', 'kf_train.cli', 'simulate', '--scenario', 'rail',
                    '--duration', str(fixes // 10), '--seed', '7', '--output', bag]
        subprocess.run(simulate, check=True, capture_output=True)
        began = time.perf_counter()
        result = subprocess.run([sys.executable, '-m', 'kf_train.cli', 'tune', bag, '-o',
                                 os.path.join(directory, 'params.yaml')],
                                capture_output=True, text=True)
        seconds = time.perf_counter() - began
    found = FIT.search(result.stdout)
    if result.returncode != 0 or found is None:
        return [('11', 'kf-train tune (rail)', f'{fixes} fixes', 'failed: '
                 + (result.stderr.strip().splitlines() or ['no report'])[-1], '', '')]
    passes, settings, fit_s, stop = found.groups()
    kept = 'kept the start' if 'kept the start' in result.stdout else 'written'
    case = f'simulated bag, {fixes} fixes, realistic receiver, defaults as the start'
    return [('11', 'kf-train tune (rail): the fit', case,
             f'{float(fit_s):.1f} s ({passes} passes, {settings} settings; {stop})', '',
             f'<= {TARGET_S:g} s at 30,000 fixes: '
             + (verdict(float(fit_s) <= TARGET_S) if not quick else 'not at --quick')),
            ('11', 'kf-train tune (rail): the whole command', case,
             f'{seconds:.1f} s (start-up, the bag, the fit, the held-out scoring; {kept})',
             f'{seconds / float(fit_s):.1f}× the fit',
             f'<= {TARGET_S:g} s at 30,000 fixes: '
             + (verdict(seconds <= TARGET_S) if not quick else 'not at --quick'))]

"""
The bank's outputs, bit for bit, as the engine of issue 22 (before its speed-up) gave them.

``data/bank_golden.npz`` holds the results the bank computed for seeded inputs of four
presets (train; cv-position; car with its control u; cv-position-velocity, a 2-D
measurement): ids, own clocks, gaps in time, shared and per-object dt, predictions to
``horizon_s``, lock-step and each object alone, and the stream's carried per-object
states. Any change to the bank's arithmetic (the operands of one operation, a formula)
shows here as an inequality. Run this file as a script to write the file again (only
for a deliberate change).

Bit for bit on the OpenBLAS kernel the file was written with (Haswell: the CI runs
the unit tests under it too); on another kernel (SkylakeX's AVX-512) a matrix
product may sum in another order, and the figures differ in their last bit: at most
0.22 ε of the field's largest magnitude over these runs (≤ 50 steps of a stable
filter), so each field is held to :data:`KERNEL_ULPS` ε of that magnitude.
"""

import os

from kf_train.batch import bank, run_bank
from kf_train.presets import load_preset
import numpy as np
import pytest

GOLDEN = os.path.join(os.path.dirname(__file__), 'data', 'bank_golden.npz')
FIELDS = ('x', 'P', 'x_prior', 'P_prior', 'F', 'predicted_x', 'predicted_P')
PRESETS = ('train', 'cv-position', 'car', 'cv-position-velocity')
CLOCKS = ('shared', 'own', 'gaps')
KERNEL_ULPS = 16.0
"""How far [ε × the field's largest magnitude] another BLAS kernel's summation may go."""


def _inputs(name: str, clock: str, seed: int):
    """Return (preset, t, z, u, ids): seeded objects of 1 to 6 rows and one of 50."""
    preset = load_preset(name)
    rng = np.random.default_rng(seed)
    counts = np.concatenate([rng.integers(1, 7, 30), [50]])
    t, ids = [], []
    for k, count in enumerate(counts):
        if clock == 'shared':      # every object at 0.1, 0.2, ... s: one dt
            times = 0.1 * np.arange(1, count + 1)
        elif clock == 'own':       # each object its own clock, the same few dt
            times = rng.uniform(0.0, 0.3) + np.cumsum(rng.choice([0.05, 0.1, 0.2], count))
        else:                      # gaps: dt of ns up to many seconds
            times = np.cumsum(rng.choice([2e-9, 0.01, 0.1, 3.0, 40.0], count)
                              * rng.uniform(1.0, 1.5, count))
        t.append(times)
        ids += [10 * k + 3] * int(count)
    t, ids = np.concatenate(t), np.array(ids)
    order = np.argsort(t, kind='stable')
    t, ids = t[order], ids[order]
    z = 5.0 * t[:, None] + rng.normal(0.0, 1.0, (t.shape[0], preset.dim_z))
    u = rng.normal(0.0, 0.3, (t.shape[0], preset.dim_u)) if preset.dim_u else None
    return preset, t, z, u, ids


def _cases():
    """Yield (key, results) for every golden case, as run_bank gives them now."""
    for p, name in enumerate(PRESETS):
        for c, clock in enumerate(CLOCKS):
            preset, t, z, u, ids = _inputs(name, clock, 100 * p + c)
            for split, horizon in (('cost', None), ('lockstep', 0.7)):
                key = f'{name}|{clock}|{split}|{horizon}'
                saved = bank.LOCKSTEP_STEP_S
                if split == 'lockstep':
                    bank.LOCKSTEP_STEP_S = 0.0
                try:
                    result = run_bank(preset, t, z, u, ids, horizon_s=horizon)
                finally:
                    bank.LOCKSTEP_STEP_S = saved
                yield key, {f: getattr(result, f) for f in FIELDS
                            if getattr(result, f) is not None}
            yield f'{name}|{clock}|carried', _carried(preset, t, z, u, ids, 7 * p + c)


def _carried(preset, t, z, u, ids, seed: int) -> dict:
    """Return the lock-step from per-object states (as a stream block carries them)."""
    rng = np.random.default_rng(seed)
    n = preset.dim_x
    groups = bank.group_rows(ids)
    dt = bank.bank_time_steps(t, groups, 0.0)
    together = np.arange(groups.counts.shape[0])
    K = together.shape[0]
    x0 = rng.normal(0.0, 1.0, (n, K))
    L = rng.normal(0.0, 1.0, (K, n, n))
    P0 = np.moveaxis(L @ np.swapaxes(L, 1, 2) + np.eye(n), 0, 2).copy()
    N = t.shape[0]
    out = (np.empty((N, n)), np.empty((N, n, n)), np.empty((N, n)), np.empty((N, n, n)),
           np.empty((N, n)), np.empty((N, n, n)))
    dts, inv = np.unique(dt, return_inverse=True)
    bank._run_together(preset, dt, z, u, groups, together, x0, P0, (dts, inv.reshape(-1)),
                       1.5, out)
    return dict(zip(('x', 'P', 'x_prior', 'P_prior', 'predicted_x', 'predicted_P'), out))


def _flatten(cases) -> dict:
    """Return the cases as one flat mapping 'key|field' -> array."""
    return {f'{key}|{field}': np.asarray(value) for key, results in cases
            for field, value in results.items()}


def _same(value: np.ndarray, expected: np.ndarray) -> bool:
    """Return whether value is expected, to the summation order of a BLAS kernel."""
    if value.shape != expected.shape or value.dtype != expected.dtype:
        return False
    if value.dtype.kind != 'f' or not value.size:
        return bool(np.array_equal(value, expected))
    finite = np.isfinite(expected)
    if not np.array_equal(finite, np.isfinite(value)) \
            or not np.array_equal(value[~finite], expected[~finite], equal_nan=True):
        return False
    scale = float(np.max(np.abs(expected[finite]), initial=0.0))
    bound = KERNEL_ULPS * np.finfo(value.dtype).eps * scale
    return bool(np.all(np.abs(value[finite] - expected[finite]) <= bound))


@pytest.mark.parametrize('block', [None, 1, 5, 64])
def test_bank_equals_its_golden_results_bit_for_bit(monkeypatch, block):
    """Every output of every case equals the stored one (to a BLAS kernel's last bit)."""
    if block is not None:
        monkeypatch.setattr(bank, 'LOCKSTEP_BLOCK', block, raising=False)
    with np.load(GOLDEN) as golden:
        expected = dict(golden)
    got = _flatten(_cases())
    assert sorted(got) == sorted(expected)
    for key, value in got.items():
        assert value.dtype == expected[key].dtype, key
        assert _same(value, expected[key]), key


def test_the_golden_comparison_sees_a_change_beyond_a_kernels_rounding():
    """A change of a few ε passes, one of a part in 10¹³ does not; NaN must match NaN."""
    expected = np.array([1.0, -3.0, np.nan, 0.5])
    eps = np.finfo(float).eps
    assert _same(expected + 2 * eps, expected)
    assert not _same(expected + np.array([0.0, 3e-13, 0.0, 0.0]), expected)
    assert not _same(np.array([1.0, -3.0, 0.0, 0.5]), expected)
    assert not _same(expected.astype(np.float32), expected)


if __name__ == '__main__':
    os.makedirs(os.path.dirname(GOLDEN), exist_ok=True)
    np.savez_compressed(GOLDEN, **_flatten(_cases()))

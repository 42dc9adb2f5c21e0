"""
The replay's bulk text paths (kf_train.io.csvio) equal the plain ones exactly.

The writer must give Python's ``repr`` for every double, the reader ``float()`` for
every plain decimal, and the replay's output must be the same bytes whichever reader
took the input, and the same numbers as the row-by-row filter.
"""

import math
import os
import struct

from hypothesis import given, settings, strategies as st
from kf_train.batch import run_series
from kf_train.cli.replay import main
from kf_train.io import csv_tables, csvio, read_table
from kf_train.presets import load_preset
import numpy as np
import pytest

# Doubles whose text is hard to get right: powers of two and ten and their
# neighbours, the fixed/scientific switches of repr (1e-4, 1e16), exact decimal ties
# at 15–17 digits, the ends of the fast range (1e±280) and of the doubles.
SPECIAL = [
    0.0, -0.0, 1.0, -1.0, 0.5, 0.25, 2.0, 1024.0, 0.1, 0.2, 0.3, 1 / 3, 2 / 3,
    1e-4, 9.999999999999999e-05, 1e-5, 1e15, 1e16, 9999999999999998.0, 1e17, 1e22, 1e23,
    123456789012345678.0, 1000000000000000.5, 1000000000000005.0, 9007199254740993.0,
    4503599627370497.5, 0.30000000000000004, 5e-324, 2.2250738585072014e-308,
    1.7976931348623157e308, 1e280, 1e-280, 9.99e279, 1.01e-280, 123.456, -0.001,
    math.inf, -math.inf, math.nan, 2.0 ** -20, 2.0 ** 60, 2.0 ** 53 + 2.0,
]


def _neighbours(x: float, k: int = 3):
    """Return the k doubles on either side of x (and x)."""
    out = [x]
    up = down = x
    for _ in range(k):
        up, down = math.nextafter(up, math.inf), math.nextafter(down, -math.inf)
        out += [up, down]
    return out


def _special_values() -> np.ndarray:
    """Return SPECIAL with every finite value's neighbours and negatives."""
    values = []
    for x in SPECIAL:
        values += _neighbours(x) if math.isfinite(x) else [x]
    values += [10.0 ** k for k in range(-300, 301)]
    for k in range(-1074, 1024):    # the gap below a power of two is half the gap above
        values += _neighbours(2.0 ** k, 1)
    return np.array(values + [-v for v in values])


def _same_text(values) -> None:
    """Assert that format_values gives repr() for every value."""
    values = np.asarray(values, dtype=float)
    got = csvio.format_values(values)
    expected = [repr(float(v)) for v in values]
    bad = [(g, e) for g, e in zip(got, expected) if g != e]
    assert len(got) == len(expected) and not bad, bad[:10]


def test_writer_equals_repr_on_hard_values():
    """Powers, boundaries, ties, subnormals, inf and NaN: the text is repr's."""
    _same_text(_special_values())


def test_writer_equals_repr_on_random_bit_patterns():
    """200 000 random doubles over the whole range (any exponent, any sign)."""
    rng = np.random.default_rng(11)
    bits = rng.integers(0, 2 ** 63, 200_000, dtype=np.int64).view(np.float64)
    bits = np.where(rng.random(bits.shape) < 0.5, -bits, bits)
    _same_text(bits)


def test_writer_equals_repr_on_short_decimals():
    """Decimals of 1 to 17 digits (the shortest forms have every length)."""
    rng = np.random.default_rng(12)
    digits = rng.integers(1, 18, 50_000)
    mantissa = np.array([int(rng.integers(10 ** (d - 1), 10 ** d)) for d in digits],
                        dtype=float)
    _same_text(mantissa * 10.0 ** rng.integers(-25, 25, digits.shape[0]))
    _same_text(np.arange(-2000, 2000) / 8.0)     # exact binary fractions
    _same_text(0.1 * np.arange(1, 20000))          # a typical time column


@settings(max_examples=300, deadline=None)
@given(st.lists(st.floats(allow_nan=True, allow_infinity=True), min_size=1, max_size=50))
def test_writer_equals_repr_property(values):
    """Any doubles hypothesis finds: repr's text."""
    _same_text(values)


def test_reader_equals_float():
    """Every plain decimal reads as float() reads it; odd text is left to the caller."""
    rng = np.random.default_rng(13)
    values = np.concatenate([_special_values(), rng.standard_normal(20_000) * 10.0 ** (
        rng.integers(-8, 18, 20_000))])
    values = values[np.isfinite(values)]
    texts = [repr(float(v)) for v in values]
    texts += ['9007199254740993', '1.', '.5', '-.5', '+3.25', '00001.5000', '0', '-0',
              '0.000000000000000000001', '123456789012345678', '1234567890123456789',
              '99999999999999999999', '1e5', '-2.5E-3', '12345678901234567890123',
              '0.1000000000000000055511151231257827', '4503599627370497.5',
              '1000000000000000.5', '2.2250738585072011e-308', '1e400', '9.87654321e-300']
    body = '\n'.join(texts).encode('ascii')
    got = csvio.parse_rows(body, 1)[:, 0]
    expected = np.array([float(t) for t in texts])
    same = (got == expected) | (np.isnan(got) & np.isnan(expected))
    assert np.all(same & (np.signbit(got) == np.signbit(expected))), \
        [t for t, s in zip(texts, same) if not s][:10]
    for odd in (b'1,,2\n3,4,5', b'1,2\n3', b'1, 2', b'1,a', b'1.2.3,4', b'--1,2',
                b'1,2\n\n3,4', b'1_0,2', b'inf,2', b'"1",2', b'1e,2', b'.,2', b'-,2'):
        assert csvio.parse_rows(odd, 2) is None, odd


@settings(max_examples=200, deadline=None)
@given(st.lists(st.floats(allow_nan=False, allow_infinity=False), min_size=1, max_size=40))
def test_text_round_trip_is_exact(values):
    """format_rows then parse_rows gives back the same doubles, bit for bit."""
    array = np.array(values, dtype=float)
    body = csvio.format_rows([array, -array]).rstrip(b'\n')
    back = csvio.parse_rows(body, 2)
    assert back is not None
    assert np.array_equal(back[:, 0].view(np.int64), array.view(np.int64))
    assert np.array_equal(back[:, 1].view(np.int64), (-array).view(np.int64))


def test_rows_and_labels_layout():
    """Columns are comma-separated, rows end in newline, a label column goes in front."""
    text = csvio.format_rows([np.array([1.5, -2.0]), np.array([1e-7, 3.0])],
                             prefix=(csvio.format_labels(['a', 'bé']), np.array([1, 0])))
    assert text.decode('utf-8') == 'bé,1.5,1e-07\na,-2.0,3.0\n'
    assert csvio.format_rows([np.array([0.1, 0.2])], 1, 2) == b'0.2\n'
    assert csvio.format_rows([np.array([])]) == b''
    with pytest.raises(ValueError, match='columns must be vectors of one length'):
        csvio.format_rows([np.ones(3), np.ones(2)])
    codes, labels = csvio.parse_labels(b'x7,1\ny,2\nx7,3', np.array([0, 5, 9]),
                                       np.array([2, 6, 11]))
    assert labels == ['x7', 'y'] and codes.tolist() == [0, 1, 0]
    assert csvio.parse_labels(b' a', np.array([0]), np.array([2])) is None
    body = b'locomotive-12,a,locomotive-12,locomotive-2'
    starts = np.array([0, 14, 16, 30])
    codes, labels = csvio.parse_labels(body, starts, np.array([13, 15, 29, 42]))
    assert labels == ['a', 'locomotive-12', 'locomotive-2']
    assert codes.tolist() == [1, 0, 1, 2]


def _write_rows(path, header, rows) -> None:
    """Write a CSV with repr() numbers."""
    with open(path, 'w') as stream:
        stream.write(','.join(header) + '\n')
        for row in rows:
            stream.write(','.join(v if isinstance(v, str) else repr(float(v)) for v in row)
                         + '\n')


@pytest.mark.parametrize('name', ['train', 'car', 'robot-exact', 'cv-position-velocity'])
def test_replay_output_is_the_plain_text_of_the_plain_path(tmp_path, name):
    """
    The replay's bytes are repr() of the vectorised numbers, whichever reader ran.

    A quoted extra column sends the input through the csv-module reader instead of the
    bulk one: the output bytes must not change. The numbers equal run_series (1e-9).
    """
    preset = load_preset(name)
    rng = np.random.default_rng(PRESET_INDEX[name])
    N = 3000
    t = np.cumsum(preset.nominal_period_s * rng.uniform(0.5, 1.5, N))
    z = 0.5 * t[:, None] + rng.standard_normal((N, preset.dim_z)) * 10.0 ** rng.integers(
        -6, 6, (N, preset.dim_z))
    u = rng.standard_normal((N, preset.dim_u)) if preset.dim_u else None
    names = ['t'] + [c[0] for c in preset.measurement_columns()]
    names += [] if u is None else ['u']
    columns = [t] + list(z.T) + ([] if u is None else [u[:, 0]])
    plain, quoted = tmp_path / 'plain.csv', tmp_path / 'quoted.csv'
    _write_rows(plain, names, zip(*columns))
    _write_rows(quoted, names + ['note'], [r + ('"a, b"',) for r in zip(*columns)])
    outputs = []
    for source in (plain, quoted):
        target = tmp_path / (source.stem + '.out.csv')
        assert main(['--preset', name, str(source), '-o', str(target), '--horizon', '1']) == 0
        outputs.append(target.read_bytes())
    assert outputs[0] == outputs[1]
    lines = outputs[0].decode('ascii').splitlines()
    header = lines[0].split(',')
    table = read_table(str(tmp_path / 'plain.out.csv'), [(h,) for h in header])
    # Every line is the repr() of the numbers it holds (shortest round trip)
    for line, row in zip(lines[1:], zip(*[table.columns[h] for h in header])):
        assert line == ','.join(repr(float(v)) for v in row)
    # The vectorised replay and run_series differ by rounding only. The first-order
    # bound of test_presets.ATOL, summed with the actual closed-loop products over
    # these 3000 rows (noise up to 1e6 m, so |K y| is large), is <= 6e-11 of the row's
    # scale max(1, |x_k|) for car, robot-exact and cv-position-velocity, <= 4e-12 for
    # the variances, but 1.6e-8 for train, whose Q is too small to forget anything.
    # The prediction 1 s ahead multiplies it by |F(1 s)| <= 2. (Measured: <= 6e-12.)
    tol = ROW_TOLERANCE.get(name, 1e-9)
    reference = run_series(preset, t, z, u, horizon_s=1.0)
    states = np.column_stack([table.columns[s] for s in preset.state_names])
    for got, want in ((states, reference.x),
                      (np.column_stack([table.columns['predicted_' + s]
                                        for s in preset.state_names]),
                       reference.predicted_x),
                      (np.column_stack([table.columns['var_' + s]
                                        for s in preset.state_names]),
                       np.diagonal(reference.P, axis1=1, axis2=2))):
        scale = np.maximum(1.0, np.max(np.abs(want), axis=1, keepdims=True))
        assert np.all(np.abs(got - want) <= tol * scale), np.max(np.abs(got - want) / scale)


PRESET_INDEX = {'train': 1, 'car': 2, 'robot-exact': 3, 'cv-position-velocity': 4}
# Row-scale tolerances where 1e-9 is below the rounding bound (see the test above).
ROW_TOLERANCE = {'train': 5e-8}


def test_bulk_reader_errors_still_name_line_and_column(tmp_path, capsys):
    """A bad cell deep in a large plain file: the message names its line and column."""
    source, target = tmp_path / 'in.csv', tmp_path / 'out.csv'
    N = 50_000
    t = 0.1 * np.arange(1, N + 1)
    rows = [(a, b) for a, b in zip(t, t)]
    rows[41_234] = (t[41_234], 'nan')
    _write_rows(source, ['t', 'z_position'], rows)
    assert main(['--preset', 'train', str(source), '-o', str(target)]) == 1
    err = capsys.readouterr().err
    assert f"{source} line 41236, column 'z_position': 'nan' is not a finite number" in err
    assert not target.exists()
    rows[41_234] = (t[41_234 - 1], 1.0)
    _write_rows(source, ['t', 'z_position'], rows)
    assert main(['--preset', 'train', str(source), '-o', str(target)]) == 1
    assert "line 41236, column 't'" in capsys.readouterr().err
    assert os.listdir(tmp_path) == ['in.csv']


def test_bytes_with_a_byte_order_mark_and_crlf(tmp_path):
    """A UTF-8 BOM and CRLF line ends read like plain text."""
    source, target = tmp_path / 'in.csv', tmp_path / 'out.csv'
    source.write_bytes(b'\xef\xbb\xbft,z_position\r\n0.1,1.0\r\n0.2,2.0\r\n')
    assert main(['--preset', 'train', str(source), '-o', str(target)]) == 0
    assert target.read_text().startswith('t,position,')
    source.write_bytes(b't,z_position\n0.1,1.0\n0.2,\xff\n')
    assert main(['--preset', 'train', str(source), '-o', str(target)]) == 1


def test_power_table_is_exact():
    """The double-double powers of ten are the correctly rounded 10^k and remainder."""
    from fractions import Fraction
    T = csv_tables._tables()
    for k in (-300, -23, -1, 0, 1, 22, 23, 300):
        i = k - csv_tables._K_MIN
        exact = Fraction(10) ** k
        assert T.p_hi[i] == float(exact)
        assert T.p_lo[i] == float(exact - Fraction(float(exact)))
        assert struct.pack('<d', T.p_hh[i] + T.p_hl[i]) == struct.pack('<d', T.p_hi[i])

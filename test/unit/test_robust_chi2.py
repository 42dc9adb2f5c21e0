"""Tests of kf_train.filters.chi2: the scipy-free χ² distribution, checked against scipy."""

import math
import subprocess
import sys

from kf_train.filters import chi2_cdf, chi2_mean_bounds, chi2_quantile, chi2_sf
import pytest
from scipy import stats

DOFS = [0.5, 1, 2, 3, 4, 5, 7, 10, 30, 100, 200, 1000, 5000, 20000, 100000]
PROBABILITIES = [1e-12, 1e-6, 0.001, 0.005, 0.01, 0.1, 0.3, 0.5, 0.7, 0.9, 0.99, 0.995,
                 0.999, 0.9999, 1 - 1e-8, 1 - 1e-12]


@pytest.mark.parametrize('dof', DOFS)
def test_quantile_matches_scipy(dof):
    """
    The quantile agrees with scipy.stats.chi2.ppf to 1e-9 relative, tails included.

    Inverting the CDF divides its relative error δ (_exponent_rounding: ~1e-14 at small
    dof, 1.1e-9 at dof = 1e5) by x·f(x)/F(x) (or /sf): >= dof/2 in the left tail,
    growing with x in the right one, ~180 at the centre for dof = 1e5. So the quantiles
    stay well within 1e-9; measured <= 2e-13.
    """
    for p in PROBABILITIES:
        expected = stats.chi2.ppf(p, dof)
        assert chi2_quantile(p, dof) == pytest.approx(expected, rel=1e-9, abs=0.0), p


def _exponent_rounding(x, dof):
    """
    Return how far apart the rounding of a·ln(x/2) − x/2 − lnΓ(a) may put two results.

    a = dof/2. Both libraries scale a series by exp of that exponent. Its terms reach
    ~1e6 at dof = 1e5 and cancel to O(ln): each is rounded (ln and lnΓ within a few
    ulp), so exp(...) is off by up to ~4u·(a|ln(x/2)| + x/2 + |lnΓ(a)|) relative on
    each side (u = 2⁻⁵³), 8u·(...) between the two: returned.
    """
    a = 0.5 * dof
    terms = a * abs(math.log(0.5 * x)) + 0.5 * x + abs(math.lgamma(a))
    return 8.0 * 2.0 ** -53 * terms


@pytest.mark.parametrize('dof', DOFS)
def test_cdf_and_sf_match_scipy(dof):
    """
    CDF and survival function agree with scipy where they are > 1e-300.

    To 1e-9 relative, or to twice the rounding of the exponent where that is larger:
    only at dof = 1e5, up to 2.2e-9 (see _exponent_rounding). Measured: <= 8e-11.
    """
    for x in [1e-6, 0.1, 1.0, dof / 2, dof, 1.5 * dof, 3 * dof + 10]:
        rel = max(1e-9, 2.0 * _exponent_rounding(x, dof))
        for ours, theirs in ((chi2_cdf(x, dof), stats.chi2.cdf(x, dof)),
                             (chi2_sf(x, dof), stats.chi2.sf(x, dof))):
            if theirs > 1e-300:
                assert ours == pytest.approx(theirs, rel=rel, abs=0.0), (x, ours, theirs)


def test_quantile_inverts_cdf():
    """cdf(quantile(p)) = p, and the ends map to 0 and inf."""
    for dof in (1, 2, 9):
        for p in (0.01, 0.5, 0.99):
            assert chi2_cdf(chi2_quantile(p, dof), dof) == pytest.approx(p, rel=1e-12)
        assert chi2_quantile(0.0, dof) == 0.0
        assert chi2_quantile(1.0, dof) == math.inf
        assert chi2_cdf(0.0, dof) == 0.0 and chi2_sf(math.inf, dof) == 0.0


def test_mean_bounds_match_scipy():
    """The bounds of a mean of n χ²(m) values are χ²(n m) quantiles over n."""
    for count, dof in ((1, 1), (10, 1), (100, 1), (100, 2), (5000, 1)):
        lower, upper = chi2_mean_bounds(count, dof)
        assert lower == pytest.approx(stats.chi2.ppf(0.005, count * dof) / count, rel=1e-9)
        assert upper == pytest.approx(stats.chi2.ppf(0.995, count * dof) / count, rel=1e-9)
    lower, upper = chi2_mean_bounds(20, 1, confidence=0.9)
    assert upper == pytest.approx(stats.chi2.ppf(0.95, 20) / 20, rel=1e-9)


@pytest.mark.parametrize('call, name', [
    (lambda: chi2_quantile(0.5, 0), 'dof'),
    (lambda: chi2_quantile(0.5, -1), 'dof'),
    (lambda: chi2_quantile(0.5, math.nan), 'dof'),
    (lambda: chi2_quantile(0.5, 'x'), 'dof'),
    (lambda: chi2_quantile(1.5, 1), 'p'),
    (lambda: chi2_quantile(-0.1, 1), 'p'),
    (lambda: chi2_quantile(math.nan, 1), 'p'),
    (lambda: chi2_quantile(None, 1), 'p'),
    (lambda: chi2_cdf(1.0, 0), 'dof'),
    (lambda: chi2_mean_bounds(0, 1), 'count'),
    (lambda: chi2_mean_bounds(1.5, 1), 'count'),
    (lambda: chi2_mean_bounds(10, 1, confidence=1.0), 'confidence'),
])
def test_invalid_arguments(call, name):
    """Invalid arguments raise ValueError naming the argument."""
    with pytest.raises(ValueError, match=rf'^{name} must'):
        call()


def test_core_and_offline_commands_import_neither_scipy_nor_ros():
    """
    The core and the offline verbs pull in neither scipy nor any ROS package.

    The nodes are held to the same for scipy by test/integration/test_bench.py.
    """
    code = ('import sys, kf_train.core, kf_train.filters.chi2, kf_train.cli.replay, '
            'kf_train.cli.compare, kf_train.evaluate, kf_train.replay\n'
            'print(sorted({m.split(".")[0] for m in sys.modules} & {"scipy", "rclpy", '
            '"rcl_interfaces", "geometry_msgs", "nav_msgs"}))')
    result = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True,
                            timeout=60, check=True)
    assert result.stdout.strip() == '[]'

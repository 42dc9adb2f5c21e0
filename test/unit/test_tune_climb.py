"""The rail fit's optimiser: never below its start, one answer from any start, reasons."""

import math

from kf_train.batch import RailNoise
from kf_train.tune.climb import cheap_derivatives, cheap_stencil, climb
import numpy as np
import pytest

NAMES = ['acceleration_noise', 'command_noise', 'measurement_variance']


def _fit(likelihoods, start, **kwargs):
    """Run the rail fit on a synthetic ℓ (scipy-free)."""
    from kf_train.tune import fit_rail_noise
    return fit_rail_noise(likelihoods, kwargs.pop('names', NAMES), start, start, rows=1000,
                          **kwargs)


def _log(settings, names=NAMES):
    """Return log θ of each setting's named fields (K, n)."""
    with np.errstate(divide='ignore'):
        return np.log([[getattr(s, n) for n in names] for s in settings])


def test_the_cheap_stencil_is_exact_on_a_quadratic():
    """Gradient and Hessian exact on a quadratic (its third and fourth derivatives are 0)."""
    A = np.array([[-3.0, 0.5, 0.2], [0.5, -2.0, -0.4], [0.2, -0.4, -1.0]])
    b = np.array([0.3, -0.1, 2.0])
    v0 = np.array([0.1, -0.2, 0.3])
    points = v0 + cheap_stencil(3)
    values = np.array([0.5 * p @ A @ p + b @ p for p in points])
    f, g, H = cheap_derivatives(values, 3)
    # central differences of a quadratic are exact to rounding (|f| ~ 1, h² = 1e-4: 1e-11)
    np.testing.assert_allclose(g, A @ v0 + b, atol=1e-9)
    np.testing.assert_allclose(H, A, atol=1e-9)


def test_a_climb_on_a_kinked_noisy_likelihood_never_ends_below_its_start():
    """ℓ = −|v − m|₁ plus a deterministic ripple: a Newton model is wrong everywhere."""
    m = np.array([1.0, -2.0])

    def objective(points):
        ripple = 1e-3 * np.sin(1e3 * points).sum(axis=1)
        return -np.abs(points - m).sum(axis=1) + ripple
    for start in (np.array([4.0, 3.0]), np.array([-5.0, -6.0]), m + 1e-3):
        start_ll = float(objective(start[None])[0])
        result = climb(objective, start, np.full(2, -30.0), np.full(2, 30.0))
        assert result.log_likelihood >= start_ll
        assert result.log_likelihood == pytest.approx(float(objective(result.vector[None])[0]))
    # from far off it gets near the kink (within the ripple's reach, ~1e-3 · n)
    assert np.abs(climb(objective, np.array([4.0, 3.0]), np.full(2, -30.0),
                        np.full(2, 30.0)).vector - m).max() < 0.05


def test_a_start_at_the_maximum_is_kept_and_said_to_be():
    """Nothing beats the setting in use by MIN_GAIN: the fit returns it unchanged."""
    m = np.log([3e-4, 2e-5, 1.1])

    def likelihoods(settings):
        return -0.5 * np.sum(((_log(settings) - m) / 0.3) ** 2, axis=1)
    start = RailNoise(3e-4, 2e-5, 1e-6, 1.1)
    fit = _fit(likelihoods, start)
    assert not fit.improved and fit.setting == start
    assert fit.log_likelihood == fit.start_log_likelihood


def test_three_starts_give_the_same_answer_to_the_printed_digits():
    """From the maximum's neighbourhood, a decade off and two decades off: 4 digits agree."""
    m = np.log([3e-4, 2e-5, 1.1])
    sd = np.array([0.3, 0.5, 0.02])

    def likelihoods(settings):
        v = _log(settings)
        # a non-quadratic ℓ (quartic terms), so Newton needs several steps
        u = (v - m) / sd
        return -0.5 * np.sum(u ** 2, axis=1) - 0.05 * np.sum(u ** 4, axis=1)
    answers = []
    for start in (RailNoise(2e-4, 3e-5, 1e-6, 1.0), RailNoise(3e-3, 2e-6, 1e-6, 0.5),
                  RailNoise(3e-6, 2e-3, 1e-6, 3.0)):
        fit = _fit(likelihoods, start, grid_centre=RailNoise(1e-4, 1e-4, 1e-6, 1.0))
        assert fit.log_likelihood >= fit.start_log_likelihood
        answers.append([f'{e.value:.4g}' for e in fit.estimates])
    assert answers[0] == answers[1] == answers[2] == [f'{math.exp(c):.4g}' for c in m]


def test_a_noise_the_data_do_not_excite_is_said_so():
    """ℓ does not depend on q_a at all: 'the data cannot tell', nothing excites it."""
    def likelihoods(settings):
        v = _log(settings)
        return -0.5 * ((v[:, 1] - math.log(2e-5)) / 0.3) ** 2 \
            - 0.5 * ((v[:, 2] - math.log(1.1)) / 0.02) ** 2
    fit = _fit(likelihoods, RailNoise(1e-4, 1e-4, 1e-6, 1.0))
    q_a = fit.estimates[0]
    # ℓ(q_a = 0) = ℓ̂ too: the boundary check calls it compatible with 0
    assert 'cannot tell' in q_a.reason
    assert all(e.reason == '' for e in fit.estimates[1:])


def test_two_noises_only_their_sum_is_identified_are_said_so():
    """ℓ depends on log q_a + log q_ℓ only: a singular curvature, a traded-off pair."""
    names = ['acceleration_noise', 'command_noise']

    def likelihoods(settings):
        v = _log(settings, names)
        with np.errstate(invalid='ignore'):
            total = np.where(np.isfinite(v).all(axis=1), v.sum(axis=1), -np.inf)
        # far below at 0: the boundary check does not apply
        return np.where(np.isfinite(total),
                        -0.5 * ((total - math.log(6e-9)) / 0.1) ** 2, -1e9)
    fit = _fit(likelihoods, RailNoise(1e-4, 1e-4, 1e-6, 1.0), names=names)
    for estimate in fit.estimates:
        assert not estimate.identified
        assert 'only their combination is identified' in estimate.reason


def _counted(objective):
    """Return (objective, the list of its batch sizes)."""
    sizes = []

    def counted(points):
        sizes.append(points.shape[0])
        return objective(points)
    return counted, sizes


def test_a_noise_headed_for_zero_reaches_the_floor_in_a_few_passes():
    """ℓ = ℓ(0) − aθ₂ near 0 plus a quadratic in log θ₁: held on the floor, not crawled to."""
    low, high = np.full(2, -14.0 * math.log(10.0)), np.full(2, 2.0 * math.log(10.0))

    def objective(points):
        return (-0.5 * ((points[:, 0] - math.log(3e-2)) / 0.1) ** 2
                - 5e4 * np.exp(points[:, 1]))
    counted, sizes = _counted(objective)
    start = np.log([1e-2, 1e-5])
    result = climb(counted, start, low, high)
    # one e-fold a Newton step: 20 steps (40 passes) to 1e-14; the ladder needs a few
    assert result.passes == len(sizes) <= 10
    assert result.stop.startswith('converged')
    assert result.vector[0] == pytest.approx(math.log(3e-2), abs=1e-3)
    # on a rung 8 decades down or on the floor: 5e4 θ₂ below 1e-7 either way
    assert 5e4 * math.exp(result.vector[1]) < 1e-7
    assert result.log_likelihood >= float(objective(start[None])[0])


def test_the_ladder_meets_an_interior_maximum_below_instead_of_jumping_to_zero():
    """ℓ = −B(√(θ/p) − 1)²: ℓ(0) > ℓ(start), the maximum 2 decades down; a rung finds it."""
    low, high = np.full(1, -14.0 * math.log(10.0)), np.full(1, 2.0 * math.log(10.0))
    peak = 1e-7

    def objective(points):
        return -0.01 * (np.exp(0.5 * (points[:, 0] - math.log(peak))) - 1.0) ** 2
    start = np.log([1e-5])
    # ℓ(start) = −0.81 < ℓ(0) = −0.01 < ℓ(peak) = 0, and on the floor ℓ is flat (3e-6):
    # a jump to 0 alone would stay there
    assert objective(start[None])[0] < objective(low[None])[0] < objective(np.log([[peak]]))[0]
    result = climb(objective, start, low, high)
    assert result.vector[0] == pytest.approx(math.log(peak), abs=1e-2)

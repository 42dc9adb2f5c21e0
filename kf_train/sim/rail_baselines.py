"""
The bar a rail filter has to clear: CV and CA Kalman filters tuned in hindsight on the run.

A constant-velocity KF (state [p, v], white acceleration of density q [m²/s³]) and a
constant-acceleration KF (state [p, v, a], white jerk of density q [m²/s⁵]), built on
:class:`kf_train.filters.KalmanFilter` (Joseph form). Both start at the first
measurement with v = a = 0 and the wide variances of the rail model's priors, measure
the position with R = σ², and predict ``horizon_s`` ahead with the same model.
:func:`tuned_baselines` tries every q of a grid on one run, scored as
:func:`kf_train.sim.rail_eval.score` scores (2-s prediction RMSE after the warm-up),
and keeps the best: what a tuner who knows the run could reach. The grids are those
``benchmarks/rail_eval.py`` uses for filterpy's filters, the same arithmetic.
"""

from typing import Dict, NamedTuple, Sequence

from kf_train.filters import KalmanFilter, RailModelParameters
from kf_train.sim.rail import RailRun
from kf_train.sim.rail_eval import hindsight_best, HORIZON_S, RunCase, Score, Track
from kf_train.sim.scenarios import Scenario
import numpy as np

CV_GRID = tuple(np.logspace(-1.5, 1.5, 13))
"""White-acceleration densities q tried for the CV KF [m²/s³]."""
CA_GRID = tuple(np.logspace(-3.5, 0.0, 15))
"""White-jerk densities q tried for the CA KF [m²/s⁵]."""
INITIAL_VELOCITY_STD_MPS = RailModelParameters().initial_velocity_std_mps
INITIAL_ACCELERATION_STD_MPS2 = RailModelParameters().initial_acceleration_std_mps2


def transition(dim: int, dt_s: float) -> np.ndarray:
    """Return F(dt) of the CV (dim 2) or CA (dim 3) model."""
    F = np.eye(dim)
    F[0, 1] = dt_s                                   # p' = p + dt v (+ dt²/2 a)
    if dim == 3:
        F[0, 2], F[1, 2] = dt_s * dt_s / 2.0, dt_s   # v' = v + dt a
    return F


def white_noise_Q(dim: int, dt_s: float, q: float) -> np.ndarray:
    """
    Return Q(dt) = q ∫₀^dt F(s) G Gᵀ F(s)ᵀ ds of white noise on the last derivative.

    CV (white acceleration): q [[dt³/3, dt²/2], [dt²/2, dt]]; CA (white jerk):
    q [[dt⁵/20, dt⁴/8, dt³/6], [dt⁴/8, dt³/3, dt²/2], [dt³/6, dt²/2, dt]].
    """
    d = dt_s
    if dim == 2:
        Q = np.array([[d ** 3 / 3.0, d ** 2 / 2.0], [d ** 2 / 2.0, d]])
    else:
        Q = np.array([[d ** 5 / 20.0, d ** 4 / 8.0, d ** 3 / 6.0],
                      [d ** 4 / 8.0, d ** 3 / 3.0, d ** 2 / 2.0],
                      [d ** 3 / 6.0, d ** 2 / 2.0, d]])
    return q * Q


class PolynomialKF:
    """A CV or CA KF behind the rail_eval harness (predict, update, predict_ahead)."""

    def __init__(self, dim: int, q: float, z0_m: float, noise_std_m: float = 1.0):
        """Start at [z0, 0(, 0)] with variances [σ², σ_v², (σ_a²)]."""
        if dim not in (2, 3):
            raise ValueError(f'dim must be 2 (CV) or 3 (CA), got {dim}')
        self.dim, self.q = dim, float(q)
        x0 = np.zeros(dim)
        x0[0] = z0_m
        variances = (noise_std_m ** 2, INITIAL_VELOCITY_STD_MPS ** 2,
                     INITIAL_ACCELERATION_STD_MPS2 ** 2)[:dim]
        self.filter = KalmanFilter(x0, np.diag(variances))
        self.H = np.eye(1, dim)
        self.R = np.array([[noise_std_m ** 2]])
        self._models: Dict[float, tuple] = {}

    def _model(self, dt_s: float):
        """Return (F, Q) over dt_s (kept: the steps of a run have a few distinct dt)."""
        model = self._models.get(dt_s)
        if model is None:
            model = self._models[dt_s] = (transition(self.dim, dt_s),
                                          white_noise_Q(self.dim, dt_s, self.q))
        return model

    def predict(self, dt_s: float) -> None:
        """Predict over dt_s: x = F x, P = F P Fᵀ + Q."""
        self.filter.predict(*self._model(dt_s))

    def update(self, z_m: float) -> None:
        """Correct with a position z."""
        self.filter.update(np.array([z_m]), self.H, self.R)

    def predict_ahead(self, horizon_s: float):
        """Return (x, P) horizon_s ahead; the filter is unchanged."""
        return self.filter.predict_ahead(*self._model(horizon_s))


class TunedBaseline(NamedTuple):
    """The best tuning of one baseline on one run."""

    name: str
    q: float
    score: Score
    track: Track


def tuned_baselines(scenario: Scenario, run: RailRun, noise_std_m: float = 1.0,
                    cv_grid: Sequence[float] = CV_GRID, ca_grid: Sequence[float] = CA_GRID,
                    horizon_s: float = HORIZON_S) -> Dict[str, TunedBaseline]:
    """Return {'CV': ..., 'CA': ...}: each KF at its best q of the grid on this run."""
    case = RunCase('run', 0, scenario, run)
    result = {}
    for name, dim, grid in (('CV', 2, cv_grid), ('CA', 3, ca_grid)):
        def maker_for(q, dim=dim):
            return lambda z0: PolynomialKF(dim, q, z0, noise_std_m)
        q, best_score, best_track = hindsight_best(maker_for, grid, case, horizon_s)
        result[name] = TunedBaseline(name, float(q), best_score, best_track)
    return result

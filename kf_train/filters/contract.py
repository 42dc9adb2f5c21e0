"""
The model contract: what the streaming estimator needs from a model, typed once.

The estimator (:mod:`kf_train.estimator`) keeps its states as (x, P) pairs and rewinds
by going back to an older pair, so every model it runs is *pure*: steps take (x, P)
and return new arrays. :class:`StepModel` is that contract (a :class:`typing.Protocol`,
checked statically; ``isinstance(model, StepModel)`` checks the names at run time):

* ``predict(x, P, dt_s, u=None) -> (x, P)``: the prediction over dt_s [s] (u
  required iff the model has a control input, ``control_names`` not empty);
* ``update(x, P, z, R=None) -> (x, P, UpdateResult)``: the correction by z with
  measurement noise R, an (m, m) array (None: the model's own); the
  :class:`~kf_train.filters.kalman.UpdateResult` carries the innovation y, its
  covariance S (the Gaussian likelihood N(y; 0, S) of z, which the χ² gate and the
  tuners read), the NIS and the gain;
* ``predict_update(x, P, dt_s, z, R=None) -> (x, P, UpdateResult)``: predict then
  update in one call, without control input: the estimator fuses every in-order
  measurement of a preset without controls with it;
* ``predict_ahead(x, P, dt_s, u=None) -> (x, P)``: the look-ahead the estimator
  publishes; it never changes anything a later step reads;
* ``widen(x, P, jump) -> (x, P)``: the state with a jump of covariance ``jump`` the
  track missed (a lock-out that keeps the track, :mod:`kf_train.estimator.reacquire`);
* ``state_names``, ``measurement_names``, ``control_names``, ``dim_x``, ``dim_z``:
  the shape of x, z and u;
* what a model with more than one state behind (x, P) can tell, None (or ()) for the
  others: ``mode_names`` and ``mode_probabilities(x, P)`` (a multiple-model filter's
  regimes), ``noise_scale(x, P)`` (a learned scale on R), ``measuring(index)`` (the
  same model measuring state ``index`` directly: a second sensor, the rail IMM's
  speed).

Every model the estimator runs implements it: the linear KF and the EKF
(:class:`~kf_train.filters.models.LinearDynamicsModel`), the UKF
(:class:`~kf_train.filters.ukf.UnscentedModel`), and the estimator's adapters (the
train's closed form, the particle filters, the rail IMM). A model without a fused step
inherits :class:`PredictThenUpdate`: its ``predict_update`` is literally ``predict``
then ``update`` (the same numbers) and its ``predict_ahead`` is ``predict``. A model
that has one (the rail IMM, whose state between the two is never combined into an
(x, P)) overrides them.
"""

from typing import List, Optional, Protocol, runtime_checkable, Sequence, Tuple

from kf_train.filters.kalman import UpdateResult
import numpy as np


def regime_columns(mode_names: Sequence[str]) -> List[str]:
    """Return the names of the regime probabilities in outputs: ``p_<mode>`` per mode."""
    return [f'p_{name}' for name in mode_names]


@runtime_checkable
class StepModel(Protocol):
    """The pure steps and shape the streaming estimator needs (see the module docstring)."""

    state_names: Tuple[str, ...]
    measurement_names: Tuple[str, ...]
    control_names: Tuple[str, ...]
    dim_x: int
    dim_z: int
    mode_names: Tuple[str, ...]

    def predict(self, x: np.ndarray, P: np.ndarray, dt_s: float, u=None
                ) -> Tuple[np.ndarray, np.ndarray]:
        """Return (x, P) predicted over dt_s (with control u, iff the model has one)."""

    def update(self, x: np.ndarray, P: np.ndarray, z: np.ndarray,
               R: Optional[np.ndarray] = None) -> Tuple[np.ndarray, np.ndarray, UpdateResult]:
        """Return (x, P, innovation statistics) after measurement z of noise R (m, m)."""

    def predict_update(self, x: np.ndarray, P: np.ndarray, dt_s: float, z: np.ndarray,
                       R: Optional[np.ndarray] = None
                       ) -> Tuple[np.ndarray, np.ndarray, UpdateResult]:
        """Return :meth:`update` after :meth:`predict` over dt_s (no control input)."""

    def predict_ahead(self, x: np.ndarray, P: np.ndarray, dt_s: float, u=None
                      ) -> Tuple[np.ndarray, np.ndarray]:
        """Return (x, P) dt_s ahead, changing nothing a later step reads."""

    def widen(self, x: np.ndarray, P: np.ndarray, jump: np.ndarray
              ) -> Tuple[np.ndarray, np.ndarray]:
        """Return the state (x, P + jump): a jump of covariance ``jump`` the track missed."""

    def mode_probabilities(self, x: np.ndarray, P: np.ndarray) -> Optional[np.ndarray]:
        """Return the probabilities of ``mode_names`` behind (x, P), or None (one model)."""

    def noise_scale(self, x: np.ndarray, P: np.ndarray) -> Optional[float]:
        """Return the learned scale on R behind (x, P), or None (R as given)."""

    def error_walk_rate_hz(self, x: np.ndarray, P: np.ndarray) -> Optional[float]:
        """Return the learned rate of the measured position's error walk, or None (none)."""

    def measuring(self, index: int) -> Optional['StepModel']:
        """Return the model measuring state ``index`` directly, or None if it cannot."""


class PredictThenUpdate:
    """The steps of a model without a fused step, built from its predict and update."""

    mode_names: Tuple[str, ...] = ()
    """One model: no regimes."""

    def predict_update(self, x, P, dt_s: float, z, R=None):
        """Return ``update(*predict(x, P, dt_s), z, R)``: the same numbers, one call."""
        x, P = self.predict(x, P, dt_s)
        return self.update(x, P, z, R)

    def predict_ahead(self, x, P, dt_s: float, u=None):
        """Return ``predict(x, P, dt_s, u)`` (pure: nothing is kept)."""
        return self.predict(x, P, dt_s, u)

    def widen(self, x, P, jump):
        """Return (a new x, P + jump): a state of its own, however the model keeps them."""
        return np.array(x, dtype=float), P + jump

    def mode_probabilities(self, x, P) -> None:
        """Return None: one model, no regimes."""
        return None

    def noise_scale(self, x, P) -> None:
        """Return None: R is used as given."""
        return None

    def error_walk_rate_hz(self, x, P) -> None:
        """Return None: the measurement error is white."""
        return None

    def measuring(self, index: int) -> None:
        """Return None: no second sensor of a single state."""
        return None

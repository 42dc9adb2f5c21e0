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
* ``state_names``, ``measurement_names``, ``control_names``, ``dim_x``, ``dim_z``:
  the shape of x, z and u.

Every model the estimator runs implements it: the linear KF and the EKF
(:class:`~kf_train.filters.models.LinearDynamicsModel`), the UKF
(:class:`~kf_train.filters.ukf.UnscentedModel`), and the estimator's adapters (the
train's closed form, the particle filters, the rail IMM). A model without a fused step
inherits :class:`PredictThenUpdate`: its ``predict_update`` is literally ``predict``
then ``update`` (the same numbers) and its ``predict_ahead`` is ``predict``. A model
that has one (the rail IMM, whose state between the two is never combined into an
(x, P)) overrides them.
"""

from typing import Optional, Protocol, runtime_checkable, Tuple

from kf_train.filters.kalman import UpdateResult
import numpy as np


@runtime_checkable
class StepModel(Protocol):
    """The pure steps and shape the streaming estimator needs (see the module docstring)."""

    state_names: Tuple[str, ...]
    measurement_names: Tuple[str, ...]
    control_names: Tuple[str, ...]
    dim_x: int
    dim_z: int

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


class PredictThenUpdate:
    """The steps of a model without a fused step, built from its predict and update."""

    def predict_update(self, x, P, dt_s: float, z, R=None):
        """Return ``update(*predict(x, P, dt_s), z, R)``: the same numbers, one call."""
        x, P = self.predict(x, P, dt_s)
        return self.update(x, P, z, R)

    def predict_ahead(self, x, P, dt_s: float, u=None):
        """Return ``predict(x, P, dt_s, u)`` (pure: nothing is kept)."""
        return self.predict(x, P, dt_s, u)

"""
An IMM behind the pure model contract (:class:`~kf_train.filters.contract.StepModel`).

The streaming estimator (kf_train.estimator.estimator) keeps its state as (x, P) pairs and
rewinds by going back to an older pair; its models are pure functions of (x, P).
An IMM's state is more than (x, P): per-mode means, covariances and probabilities.
:class:`IMMModel` returns the combined (x, P) and remembers, under the id of the
returned mean, the whole :class:`~kf_train.filters.imm.IMMState` behind it (the
particle filter's adapter in the estimator does the same with its particles). A step
given a mean it returned continues from that state, so rewinding to an old (x, P)
and replaying repeats the original steps bit for bit; a mean it never returned (an
initialisation, ``set_state``) starts every mode at (x, P) with the initial mode
probabilities. States are immutable, so remembering one costs a reference: it keeps no
running state of its own (:class:`~kf_train.filters.IMMFilter` is the one that does).
Its :meth:`IMMModel.predict_update` is the IMM's fused step, not predict then update.
"""

from typing import Dict, Optional, Tuple
import weakref

from kf_train.filters import IMM, IMMState, make_state, UpdateResult
import numpy as np


class IMMModel:
    """Pure (x, P) steps of an IMM, a StepModel; see the module docstring."""

    def __init__(self, imm: IMM, H, R, state_names, measurement_names=('position',),
                 probabilities=None, states: Optional[Dict[int, tuple]] = None,
                 measured: Optional[int] = None):
        """
        Wrap ``imm`` (its modes measure z = H x with default noise R).

        ``measured``: the index k of a state measured directly instead (H = e_k, a
        second sensor: :meth:`~kf_train.filters.IMM.update_component`); see
        :meth:`measuring`.
        """
        self.imm = imm
        self.mode_names = tuple(imm.mode_names)
        self.H = np.array(H, dtype=float)
        self.R = np.array(R, dtype=float)
        self.state_names = tuple(state_names)
        self.measurement_names = tuple(measurement_names)
        self.control_names = ()
        self.dim_x, self.dim_z = len(self.state_names), len(self.measurement_names)
        self.probabilities = probabilities
        self.states = {} if states is None else states
        self.measured = measured

    def measuring(self, index: int) -> 'IMMModel':
        """
        Return the model of the same IMM measuring state ``index`` directly (H = e_index).

        It shares this model's states, so a history may hold steps of both (a position,
        then a speed) and a rewind and replay repeats each step with its own model. Its
        updates need their R (a sensor of its own: no default noise).
        """
        H = np.zeros((1, self.dim_x))
        H[0, index] = 1.0
        return IMMModel(self.imm, H, self.R, self.state_names, (self.state_names[index],),
                        self.probabilities, self.states, index)

    def _update(self, state: IMMState, z, R):
        """Return the IMM's update of ``state`` by z: its own measurement or ``measured``."""
        if self.measured is None:
            return self.imm.update(state, z, R)
        return self.imm.update_component(state, z, R, self.measured)   # R required

    def state_of(self, x: np.ndarray, P: np.ndarray) -> IMMState:
        """Return the IMM state behind x (all modes at (x, P) if x is not one of ours)."""
        kept = self.states.get(id(x))
        if kept is not None and kept[0]() is x:
            return kept[1]
        return self.imm.initial_state(x, P, self.probabilities)

    def _keep(self, state: IMMState) -> Tuple[np.ndarray, np.ndarray]:
        """Return the combined (x, P) of ``state``, x remembering the state."""
        x, P = self.imm.estimate(state)
        key = id(x)
        # The weak reference tells x from a later array that reuses its id; its
        # callback drops the entry when x is freed, since nothing can rewind to it any
        # more (a plain callback: weakref.finalize costs several times as much).
        self.states[key] = (weakref.ref(x, _forget(self.states, key)), state)
        return x, P

    def predict(self, x, P, dt_s: float, u=None) -> Tuple[np.ndarray, np.ndarray]:
        """Return the combined (x, P) after an IMM prediction over dt_s."""
        return self._keep(self.imm.predict(self.state_of(x, P), dt_s, u))

    def predict_ahead(self, x, P, dt_s: float, u=None) -> Tuple[np.ndarray, np.ndarray]:
        """Return the combined (x, P) dt_s ahead (the IMM's own look-ahead)."""
        return self.imm.predict_ahead(self.state_of(x, P), dt_s, u)

    def update(self, x, P, z, R=None) -> Tuple[np.ndarray, np.ndarray, UpdateResult]:
        """Return the combined (x, P) after z, and the mixture's innovation statistics."""
        state, result = self._update(self.state_of(x, P), z, R)
        x, P = self._keep(state)
        return x, P, result

    def predict_update(self, x, P, dt_s: float, z, R=None
                       ) -> Tuple[np.ndarray, np.ndarray, UpdateResult]:
        """
        Return :meth:`update` after :meth:`predict` over dt_s, the same numbers to the bit.

        The IMM state in between is never combined into an (x, P) (nothing reads it):
        the streaming estimator fuses an in-order measurement with this one call, the
        IMM's own (:meth:`~kf_train.filters.IMM.predict_update`: one compiled call for
        the rail model).
        """
        state, result = self.imm.predict_update(self.state_of(x, P), dt_s, z, R, self.measured)
        x, P = self._keep(state)
        return x, P, result

    def widen(self, x, P, jump) -> Tuple[np.ndarray, np.ndarray]:
        """Return the state behind x with ``jump`` added to every mode's covariance."""
        state = self.state_of(x, P)
        # Probabilities and the learned noise scale are kept: only the motion jumped. A
        # mode whose dynamics pin a state (stand: v = 0) sets it again at its next step.
        return self._keep(make_state(state.means, state.covariances + jump,
                                     state.probabilities, state.noise))

    def mode_probabilities(self, x, P) -> np.ndarray:
        """Return the mode probabilities behind x (the initial ones if none)."""
        return self.state_of(x, P).probabilities.copy()

    def noise_scale(self, x, P) -> float:
        """Return the learned scale on the measurement noise behind x (1: R as given)."""
        return self.state_of(x, P).noise.scale

    def error_walk_rate_hz(self, x, P) -> Optional[float]:
        """Return the IMM's learned error-walk rate behind x, or None (the error is white)."""
        return self.imm.error_walk_rate_hz(self.state_of(x, P))


def _forget(states: Dict[int, tuple], key: int):
    """Return the weak-reference callback that drops ``states[key]`` once its mean is freed."""
    def callback(reference) -> None:
        kept = states.get(key)
        if kept is not None and kept[0] is reference:
            del states[key]
    return callback

"""
A GNSS receiver's habits as the fusion judges them: repeated epochs and held positions.

Both concern a fix equal to the newest fused position, where R is learned below the
R given (``gate_nis`` set): seeds and presets with R as given are untouched.
:class:`~kf_train.estimator.fusion.Fusion` asks :func:`repeated_epoch` first; a repeat
it lets through may be a held position (:func:`held_standstill`), and is otherwise
fused as a position.

**Repeated epochs.** A receiver repeats an epoch (its last output again, after a
dropped solution or an outage): at 31 m/s a repeat 0.2 s later is a 6-m step back.
The gate uses the R given when R is learned lower, and a learned R of a few
centimetres then weighs that step as motion. So an exact repeat is rejected when either

* its NIS on the R in use, yᵀ S⁻¹ y with S = H P Hᵀ + s R (the update's own; y is how
  far the track moved from the last fix), exceeds the gate; or
* the train was moving too fast to be there (rail_model.moved_past: its speed then, at
  the gate's lower bound, braking at once at the model's limit). After a 30-s outage
  the regimes spread over hundreds of metres and a repeat of the last fix passes the
  gate on the prediction: on a 98-minute receiver run one such repeat was fused as a
  train braked to a halt 292 m back, and the next fixes were rejected for 2 s.

Repeats count toward the lock-out as outliers do: a receiver that keeps repeating one
position says the train stands there, and ``max_consecutive_outliers`` of them
re-acquire the track on it (on a real log a receiver held one position for over 15 s
while the track coasted on at 10.8 m/s).

**Held positions.** Receivers hold their output while they see themselves standing
(Doppler below ~0.3 m/s; 76-83 % of the standing fixes on real u-blox logs repeat the
last one exactly). A held fix carries no new position: fused as one, it pins the track
to a value the receiver's slow error has since left, and the jump when the hold ends
reads as motion. What it says is that the receiver sees no speed, so it is fused as a
speed of 0 ± ``hold_speed_std_mps``, when that passes the gate and the variance given
is at most ``hold_max_variance_m2`` (a cold start's hold is not one).
"""

from typing import Optional, Tuple

from kf_train.estimator.contract import NUMERICAL_ERRORS
from kf_train.estimator.settings import Configuration
from kf_train.filters import moved_past, UpdateResult
import numpy as np


def repeated_epoch(config: Configuration, x0: np.ndarray, P0: np.ndarray, dt_s: float,
                   R: np.ndarray, result: UpdateResult) -> Optional[str]:
    """Return why a repeat of the newest position dt_s after it (at x0, P0) is one, or None."""
    threshold = config.gate_threshold
    model = config.model
    if result.nis > threshold:                               # yᵀ S⁻¹ y, S with s R
        return f'NIS {result.nis:.6g} on the R in use, gate {threshold:.6g}'
    if config.velocity_model is None:
        return None
    v = model.state_names.index('velocity')
    reach_m2 = float(P0[0, 0]) + model.noise_scale(x0, P0) * float(R[0, 0])
    if not moved_past(float(x0[v]), float(P0[v, v]), dt_s, reach_m2, threshold):
        return None
    return f'{dt_s:.6g} s after a fix at {float(x0[v]):.6g} m/s: it cannot have stopped there'


def held_standstill(config: Configuration, x0: np.ndarray, P0: np.ndarray, dt_s: float,
                    R: np.ndarray) -> Optional[Tuple[np.ndarray, np.ndarray, np.ndarray,
                                                     np.ndarray]]:
    """Return (x, P, z, R) after a held position fused as a speed of 0, or None (a position)."""
    hold = config.hold
    if hold is None or float(R[0, 0]) > hold.max_variance_m2:
        return None
    z, R = np.zeros(1), np.array([[hold.speed_variance_m2s2]])
    try:
        x, P, result = config.velocity_model.predict_update(x0, P0, dt_s, z, R)
    except NUMERICAL_ERRORS:
        return None
    return (x, P, z, R) if result.nis <= config.gate_threshold else None

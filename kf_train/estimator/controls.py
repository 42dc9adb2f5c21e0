"""
The controls buffer, and predictions split at control stamps.

A control stamped t_k is the input applied over the interval (t_{k-1}, t_k] that
*ends* at t_k (the seeds' convention: docs/presets.md); the latest value received
for a stamp is kept. See
:mod:`kf_train.estimator.estimator` for how the estimator uses them.
"""

import bisect
from typing import Dict, List, Optional, Tuple

from kf_train.filters import NS_PER_S
import numpy as np

# Controls kept at most (a control stream running while no measurement comes).
MAX_CONTROLS = 100_000


class Controls:
    """Control inputs by stamp (the latest value per stamp), sorted by stamp."""

    def __init__(self, dim_u: int):
        """Start empty; controls have ``dim_u`` components."""
        self.stamps: List[int] = []
        self.values: Dict[int, np.ndarray] = {}
        self.zero = np.zeros(dim_u)
        self.zero.setflags(write=False)

    def __len__(self) -> int:
        """Return how many stamps have a control."""
        return len(self.stamps)

    def previous_stamp(self, stamp_ns: int) -> Optional[int]:
        """Return the latest control stamp before ``stamp_ns``, or None."""
        i = bisect.bisect_left(self.stamps, stamp_ns)
        return self.stamps[i - 1] if i else None

    def put(self, stamp_ns: int, u: np.ndarray) -> Optional[np.ndarray]:
        """Store u at stamp_ns; return the value it replaces (None if new)."""
        old = self.values.get(stamp_ns)
        if old is None:
            if self.stamps and stamp_ns < self.stamps[-1]:
                bisect.insort(self.stamps, stamp_ns)
            else:
                self.stamps.append(stamp_ns)
        self.values[stamp_ns] = u
        return old

    def restore(self, stamp_ns: int, old: Optional[np.ndarray]) -> None:
        """Undo put(stamp_ns, ...) that returned ``old``."""
        if old is None:
            del self.values[stamp_ns]
            self.stamps.remove(stamp_ns)
        else:
            self.values[stamp_ns] = old

    def inside(self, t_a: int, t_b: int) -> List[int]:
        """Return the control stamps c with t_a < c < t_b, in order."""
        stamps = self.stamps
        return stamps[bisect.bisect_right(stamps, t_a):bisect.bisect_left(stamps, t_b)]

    def for_interval_ending(self, stamp_ns: int) -> Tuple[np.ndarray, bool]:
        """
        Return (u, exact): the control of the interval that ends at stamp_ns.

        Exact when a control has that stamp; else the control of the interval that
        contains it (the first later stamp), else the latest earlier one (held), else 0.
        """
        u = self.values.get(stamp_ns)
        if u is not None:
            return u, True
        i = bisect.bisect_right(self.stamps, stamp_ns)
        if i < len(self.stamps):
            return self.values[self.stamps[i]], False
        if i:
            return self.values[self.stamps[i - 1]], False
        return self.zero, False

    def prune(self, cutoff_ns: int) -> None:
        """Forget controls older than cutoff_ns but the latest of them; keep MAX_CONTROLS."""
        stamps = self.stamps
        drop = max(bisect.bisect_left(stamps, cutoff_ns) - 1, len(stamps) - MAX_CONTROLS)
        if drop > 0:
            for stamp_ns in stamps[:drop]:
                del self.values[stamp_ns]
            del stamps[:drop]

    def clear(self) -> None:
        """Forget every control."""
        self.stamps.clear()
        self.values.clear()


def propagate(controls: Optional[Controls], model, x, P, t_a: int, t_b: int,
              dt_s: Optional[float] = None):
    """
    Return (x, P, u, exact) predicted from stamp t_a to t_b.

    Without control input (``controls`` None) one step of dt = t_b - t_a (or ``dt_s``).
    With it, the step is split at the control stamps inside (t_a, t_b); ``u`` is the
    control of the last piece, ``exact`` whether it was stamped t_b.
    """
    if controls is None:
        x, P = model.predict(x, P, (t_b - t_a) / NS_PER_S if dt_s is None else dt_s)
        return x, P, None, True
    t = t_a
    for c in controls.inside(t_a, t_b):
        # x⁻ = F x + B u over (t, c], with the control of the interval ending at c
        x, P = model.predict(x, P, (c - t) / NS_PER_S, controls.values[c])
        t = c
    u, exact = controls.for_interval_ending(t_b)
    dt = dt_s if (dt_s is not None and t == t_a) else (t_b - t) / NS_PER_S
    x, P = model.predict(x, P, dt, u)
    return x, P, u, exact


def prune_controls(controls: Optional[Controls], history, last_stamp_ns: Optional[int],
                   nominal_ns: int) -> None:
    """Forget controls no replay or prediction can need any more (``history``: the kept one)."""
    if controls is None or not controls.stamps:
        return
    if history:
        first = history[0]
        cutoff = first.stamp_ns - (nominal_ns if first.kind == 'init' else 0)
    elif last_stamp_ns is not None:
        cutoff = last_stamp_ns
    else:
        # Not initialised: the first measurement may need any of them (controls
        # fed ahead of the measurements, offline); only MAX_CONTROLS bounds them.
        cutoff = controls.stamps[0]
    controls.prune(cutoff)

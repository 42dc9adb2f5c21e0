"""
Seeded sensor faults for the simulator: dropouts, outliers, delay, reordering, clock jumps, bias.

:class:`FaultInjector` turns each clean sample (stamp, position) into zero, one or
two deliveries, in the order they leave the sensor. Its random numbers come from
their own generator, derived from the simulation seed but separate from the
measurement noise, so switching a fault on or off never changes the noise of the
samples, and four uniforms are drawn for every sample whatever the settings, so
changing one probability does not reshuffle the other faults. Applied in this order:

1. bias: ``z += bias_m``;
2. outlier: with ``outlier_probability``, ``z ±= outlier_size_m`` (random sign);
3. clock jump: samples at ``t_s >= clock_jump_at_s`` (when > 0) have
   ``clock_jump_s`` added to their stamp (negative: the sensor's clock restarted);
4. dropout: with ``dropout_probability`` the sample is lost;
5. reordering: with ``reorder_probability`` a sample is held back and delivered right
   after the next delivered one (so it arrives one sample late, out of sequence);
6. delay: every delivery leaves ``delay_s`` after it was taken (a fixed latency,
   applied by the node).
"""

from dataclasses import dataclass
import math
from typing import List, NamedTuple, Optional

import numpy as np

# Distinguishes the fault generator's seed from the noise generator's seed.
FAULT_STREAM = 0x6661756C74


@dataclass(frozen=True)
class FaultSettings:
    """Fault probabilities and sizes; the defaults inject nothing."""

    dropout_probability: float = 0.0
    outlier_probability: float = 0.0
    outlier_size_m: float = 10.0
    delay_s: float = 0.0
    reorder_probability: float = 0.0
    clock_jump_at_s: float = 0.0
    """Sample time [s] from which stamps jump; 0 = never."""
    clock_jump_s: float = 0.0
    """Added to every stamp from clock_jump_at_s on [s]; negative jumps back."""
    bias_m: float = 0.0

    def validated(self) -> 'FaultSettings':
        """Return self after checking every field; raise ValueError naming the field."""
        for name in ('dropout_probability', 'outlier_probability', 'reorder_probability'):
            value = getattr(self, name)
            if not _is_number(value) or not 0.0 <= value <= 1.0:
                raise ValueError(f'{name} must be a probability in [0, 1], got {value!r}')
        for name in ('outlier_size_m', 'delay_s', 'clock_jump_at_s'):
            value = getattr(self, name)
            if not _is_number(value) or value < 0.0:
                raise ValueError(f'{name} must be a finite number >= 0, got {value!r}')
        for name in ('clock_jump_s', 'bias_m'):
            if not _is_number(getattr(self, name)):
                raise ValueError(f'{name} must be a finite number, got {getattr(self, name)!r}')
        return self


def _is_number(value) -> bool:
    """Return whether value is a finite real number (not a bool)."""
    return (isinstance(value, (int, float, np.integer, np.floating))
            and not isinstance(value, bool) and math.isfinite(value))


class Delivery(NamedTuple):
    """A measurement as it leaves the faulty sensor."""

    index: int
    """The sample index it was taken at."""
    stamp_ns: int
    position_m: float
    outlier: bool


class FaultInjector:
    """Applies :class:`FaultSettings` to a sample stream, reproducibly from a seed."""

    def __init__(self, settings: FaultSettings = FaultSettings(), seed: Optional[int] = None):
        """Validate the settings; ``seed`` None draws fresh entropy."""
        self.settings = settings.validated()
        entropy = None if seed is None else [FAULT_STREAM, int(seed)]
        self._rng = np.random.default_rng(entropy)
        self._held: Optional[Delivery] = None
        self.dropped = 0
        self.outliers = 0
        self.reordered = 0
        """Samples delivered after a later one (a held sample whose successor was
        dropped goes out alone, in order)."""

    def reconfigure(self, settings: FaultSettings) -> None:
        """Use new settings from the next sample on."""
        self.settings = settings.validated()

    def apply(self, index: int, t_s: float, stamp_ns: int,
              position_m: float) -> List[Delivery]:
        """Return what leaves the sensor after sample ``index`` taken at t_s, in order."""
        s = self.settings
        u_outlier, u_sign, u_drop, u_reorder = self._rng.random(4)
        position_m = position_m + s.bias_m
        outlier = bool(u_outlier < s.outlier_probability)
        if outlier:
            self.outliers += 1
            position_m += s.outlier_size_m if u_sign < 0.5 else -s.outlier_size_m
        stamp_ns = self.jumped_stamp_ns(t_s, stamp_ns)
        held, self._held = self._held, None
        if u_drop < s.dropout_probability:
            self.dropped += 1
            return [held] if held else []
        delivery = Delivery(index, stamp_ns, position_m, outlier)
        if held:
            self.reordered += 1
            return [delivery, held]
        if u_reorder < s.reorder_probability:
            self._held = delivery
            return []
        return [delivery]

    def jumped_stamp_ns(self, t_s: float, stamp_ns: int) -> int:
        """Return the stamp a sample taken at t_s carries, clock jump included."""
        s = self.settings
        if 0.0 < s.clock_jump_at_s <= t_s:
            return stamp_ns + int(round(s.clock_jump_s * 1e9))
        return stamp_ns

    def flush(self) -> List[Delivery]:
        """Return a held-back sample (at the end of a stream), if any."""
        held, self._held = self._held, None
        return [held] if held else []

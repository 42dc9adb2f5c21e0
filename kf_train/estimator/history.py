"""
The fused states kept for out-of-sequence fusion, and how a timeline starts and replays.

Each fused measurement is kept as an :class:`Entry` with the state right after it,
for ``history_s`` (plus one older state to rewind to). An out-of-sequence measurement
or a late control rewinds to the last entry before it and :func:`replay` re-fuses the
later ones, each with the R and model it was first fused with and the controls known
now. :func:`initial_state` is where a timeline starts (see the module docs of
:mod:`kf_train.estimator.estimator` for the two initialisation modes).
:func:`rewind_point` and :func:`replay_control` decide where a late measurement or
control goes; like the contract's checks they raise :class:`Rejected` uncounted and
change nothing the estimator keeps (a failed replay restores the controls).
"""

import bisect
import collections
from typing import Callable, Iterator, List, NamedTuple, Optional, Sequence

from kf_train.estimator.contract import NUMERICAL_ERRORS, Rejected
from kf_train.estimator.controls import Controls, propagate
from kf_train.filters import StepModel
import numpy as np


class Entry(NamedTuple):
    """One fused measurement and the state right after it, for out-of-sequence replay."""

    stamp_ns: int
    z: np.ndarray
    R: np.ndarray
    model: StepModel
    x: np.ndarray
    P: np.ndarray
    kind: str
    """'init' (initialised the filter), 'update', 'hold' (a held position fused as a
    speed of 0), or 'set' / 'reinit' (set_state, the re-initialisation after a
    lock-out: no rewinding past them)."""
    velocity: bool = False
    """A speed measurement (fused after a position of the same stamp), not a position."""


class History:
    """The entries younger than ``window_ns`` (plus one older to rewind to), oldest first."""

    def __init__(self):
        """Start empty, with the window off (0: nothing is kept)."""
        self._entries = collections.deque()
        self.window_ns = 0

    def __len__(self) -> int:
        """Return how many entries are kept."""
        return len(self._entries)

    def __iter__(self) -> Iterator[Entry]:
        """Iterate over the entries, oldest first."""
        return iter(self._entries)

    def __getitem__(self, index: int) -> Entry:
        """Return an entry (0: the oldest)."""
        return self._entries[index]

    def entries(self) -> List[Entry]:
        """Return the entries as a new list."""
        return list(self._entries)

    def replace(self, entries: Sequence[Entry]) -> None:
        """Keep exactly ``entries`` (a rewound and replayed history)."""
        self._entries = collections.deque(entries)

    def clear(self) -> None:
        """Forget every entry."""
        self._entries.clear()

    def append(self, entry: Entry) -> None:
        """Keep ``entry`` as the newest (when a window is set), untrimmed."""
        if self.window_ns > 0:
            self._entries.append(entry)

    def commit(self, entry: Entry) -> None:
        """Keep ``entry`` as the newest; forget what no rewind can reach any more."""
        if self.window_ns > 0:
            history = self._entries
            history.append(entry)
            # Keep every state younger than history_s plus one older one to rewind to.
            oldest_needed = entry.stamp_ns - self.window_ns
            while len(history) > 1 and history[1].stamp_ns <= oldest_needed:
                history.popleft()


def replay(rebuilt: List[Entry], rest: Sequence[Entry], u, controls: Optional[Controls]):
    """Return (entries, x, P, u): ``rest`` re-fused after ``rebuilt``, as first fused."""
    x, P = rebuilt[-1].x, rebuilt[-1].P
    for entry in rest:
        x, P, u, _ = propagate(controls, entry.model, x, P, rebuilt[-1].stamp_ns,
                               entry.stamp_ns)
        x, P, _ = entry.model.update(x, P, entry.z, entry.R)
        # Re-fused: an update now, even the first fix ('init'); a hold stays one.
        rebuilt.append(entry._replace(x=x, P=P, kind='hold' if entry.kind == 'hold' else 'update'))
    if not rest and u is None and controls is not None:
        u = controls.for_interval_ending(rebuilt[-1].stamp_ns)[0]
    return rebuilt, x, P, u


def initial_state(config, controls: Optional[Controls], locked_out: bool, stamp_ns: int,
                  z: np.ndarray, R: np.ndarray, model):
    """
    Return (x, P, update result or None, u, exact) of the filter initialised by z.

    ``config`` is the estimator's :class:`~kf_train.estimator.settings.Configuration`.
    In ``prior`` mode (unless ``locked_out``: the prior is what the data contradicted)
    the prior holds one nominal period before the stamp and z updates it; otherwise
    z sets the states it measures.
    """
    if config.settings.initialization == 'prior' and not locked_out:
        x, P, u, exact = propagate(
            controls, model, config.initial_state, config.initial_covariance,
            stamp_ns - config.nominal_ns, stamp_ns, config.nominal_period_s)
        x, P, result = model.update(x, P, z, R)
        return x, P, result, u, exact
    # Measured states from the measurement, the others from the initial state with
    # their first_measurement variances (the wide first_velocity_std_mps; the rail
    # preset's priors).
    x = config.initial_state.copy()
    variances = list(config.unmeasured_variances)
    for i, j in enumerate(config.selector):
        x[j] = z[i]
        variances[j] = R[i, i]
    P = np.diag(variances)
    for i, j in enumerate(config.selector):
        for k, m in enumerate(config.selector):
            if i != k:
                P[j, m] = R[i, k]
    u, exact = (None, True) if controls is None else controls.for_interval_ending(stamp_ns)
    return x, P, None, u, exact


def is_speed(entry: Entry) -> bool:
    """Return whether an entry is a measured speed (not a position, nor a held one)."""
    return entry.velocity and entry.kind != 'hold'


def rewind_point(entries: List[Entry], stamp_ns: int, last_stamp_ns: int,
                 velocity: bool = False) -> int:
    """
    Return the index an out-of-sequence stamp goes to in ``entries``, or raise Rejected.

    At one stamp a position goes before a speed (``velocity``): the order in which a
    receiver's epoch is fused whichever message came first. A hold is its stamp's
    position (fused as a speed of 0).
    """
    stamps = [entry.stamp_ns for entry in entries]
    i = bisect.bisect_left(stamps, stamp_ns)
    while i < len(stamps) and stamps[i] == stamp_ns:
        speed = is_speed(entries[i])
        if speed == velocity:
            raise Rejected('duplicate_stamp',
                           f'measurement stamp {stamp_ns} ns was fused already')
        if speed:
            break       # a position goes before the speed of its stamp
        i += 1          # a speed goes after the position of its stamp
    if velocity:
        if i == 0:
            raise Rejected('stale_stamp', (
                f'velocity stamp {stamp_ns} ns is older than the oldest state kept to '
                f'rewind to ({stamps[0] if stamps else "none"} ns)'))
        return i
    if i == 0 and (not entries or entries[0].kind != 'init'):
        what = 'the state was set' if entries else 'no state is kept (history_s)'
        raise Rejected('stale_stamp', (
            f'measurement stamp {stamp_ns} ns is not newer than the last fused one, '
            f'{last_stamp_ns} ns, and older than the oldest state to rewind to: {what}'))
    return i


class ControlReplay(NamedTuple):
    """What a control for fused intervals changed (:func:`replay_control`)."""

    entries: Optional[List[Entry]]
    """The replayed history; None when no fused estimate changed (the control is kept)."""
    x: Optional[np.ndarray] = None
    P: Optional[np.ndarray] = None
    predicted: Optional[tuple] = None
    """The prediction horizon_s ahead of the newest state."""
    replayed: int = 0
    """How many fused measurements were recomputed."""
    prune: bool = False
    """With entries None: whether controls may be pruned now (the control was new)."""


def replay_control(config, controls: Controls, entries: List[Entry], locked_out: bool,
                   stamp_ns: int, u: np.ndarray, predict_ahead: Callable) -> ControlReplay:
    """
    Put control ``u`` stamped ``stamp_ns`` into ``controls``; recompute what it changes.

    ``entries`` is the kept history (not empty). The first interval the control can
    change ends after the previous control's stamp; the history is rewound to the
    state before it and replayed with the controls known now. Raises Rejected
    (``stale_stamp``) when the states it applied to are no longer kept, and
    (``numerical``) with ``controls`` restored when the replay fails.
    """
    first = entries[0]
    prior_init = first.kind == 'init' and config.settings.initialization == 'prior'
    # Intervals ending after `floor` can be recomputed from the history.
    floor = first.stamp_ns - config.nominal_ns if prior_init else first.stamp_ns
    if stamp_ns <= floor:
        if first.kind in ('update', 'hold'):  # the states it applied to are no longer kept
            raise Rejected('stale_stamp', (
                f'control stamp {stamp_ns} ns is older than the oldest state kept to '
                f'replay from ({floor} ns; history_s = {config.settings.history_s})'))
        # It applies to a time before the filter started: kept, but nothing to redo.
        controls.put(stamp_ns, u)
        return ControlReplay(None)
    previous = controls.previous_stamp(stamp_ns)
    old = controls.put(stamp_ns, u)
    if old is not None and np.array_equal(old, u):
        return ControlReplay(None)
    # The first fused interval it can change ends after the previous control's stamp
    # (intervals up to there had their own control, or one at least as close).
    stamps = [entry.stamp_ns for entry in entries]
    start = 0 if previous is None else bisect.bisect_right(stamps, previous)
    if start == 0 and not prior_init:
        start = 1  # the first state came from a measurement or set_state, not a prediction
    if start >= len(entries):
        return ControlReplay(None, prune=True)
    try:
        if start == 0:
            x, P, _, u_end, _ = initial_state(config, controls, locked_out, first.stamp_ns,
                                              first.z, first.R, first.model)
            rebuilt, rest = [first._replace(x=x, P=P)], entries[1:]
        else:
            rebuilt, rest, u_end = entries[:start], entries[start:], None
        rebuilt, x, P, u_end = replay(rebuilt, rest, u_end, controls)
        predicted = predict_ahead(x, P, u_end)
    except NUMERICAL_ERRORS as error:
        controls.restore(stamp_ns, old)
        raise Rejected('numerical', f'replay with the control failed: {error}') from None
    return ControlReplay(rebuilt, x, P, predicted, len(entries) - start)

"""
A progress bar on stderr for long offline runs, drawn by tqdm (the extra ``[progress]``).

The bar appears only when stderr is a terminal and the run has taken more than
:data:`DELAY_S` seconds (tqdm's ``delay``): short runs, pipes, logs and tests see
nothing. Without tqdm installed there is no bar and no error. Callers report work in
batches (:meth:`Progress.advance`, :func:`counted`), so that a bar costs next to
nothing per row or message.
"""

import sys
from typing import Iterable, Iterator, Optional

DELAY_S = 2.0
"""Seconds of work before the bar is shown."""
MIN_INTERVAL_S = 0.5
"""Seconds between redraws at most."""
EVERY = 1024
"""Items between two updates of the bar by :func:`counted`."""


class Progress:
    """A bar over ``total`` units (None: a count and a rate), or nothing (see the module)."""

    def __init__(self, total: Optional[int], unit: str, description: str = '',
                 stream=None, force: Optional[bool] = None):
        """Start the bar; ``force`` True/False overrides the terminal test (for tests)."""
        stream = sys.stderr if stream is None else stream
        wanted = _is_terminal(stream) if force is None else force
        self._bar = None
        if wanted:
            try:
                from tqdm import tqdm
            except ImportError:     # the extra is optional: no bar then
                return
            self._bar = tqdm(total=total, unit=unit, desc=description or None, file=stream,
                             delay=0.0 if force else DELAY_S, mininterval=MIN_INTERVAL_S,
                             leave=False, dynamic_ncols=True, unit_scale=True)

    @property
    def active(self) -> bool:
        """Return whether a bar is drawn."""
        return self._bar is not None

    def advance(self, units: int) -> None:
        """Count ``units`` more units done."""
        if self._bar is not None:
            self._bar.update(units)

    def close(self) -> None:
        """Remove the bar."""
        if self._bar is not None:
            self._bar.close()
            self._bar = None

    def __enter__(self) -> 'Progress':
        """Return self."""
        return self

    def __exit__(self, *exc_info) -> None:
        """Remove the bar."""
        self.close()


def counted(items: Iterable, total: Optional[int], unit: str, description: str = '',
            force: Optional[bool] = None) -> Iterator:
    """Yield ``items`` unchanged, counting them on a bar (updated every :data:`EVERY`)."""
    with Progress(total, unit, description, force=force) as progress:
        if not progress.active:
            yield from items
            return
        done = 0
        for done, item in enumerate(items, 1):
            if not done % EVERY:
                progress.advance(EVERY)
            yield item
        progress.advance(done % EVERY)


def _is_terminal(stream) -> bool:
    """Return whether ``stream`` is a terminal."""
    try:
        return bool(stream.isatty())
    except (AttributeError, ValueError):
        return False

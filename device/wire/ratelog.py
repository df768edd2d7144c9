"""Log lines that a peer can provoke, at most one per peer and interval, with a count of the rest.

A host holding an authorised key can send thousands of hellos a second; each would otherwise be a
line in the device's journal.  :class:`RateLimitedLog` lets the first line of a key through, then
holds that key's lines for ``interval_s`` and says, on its next line, how many it held back.
"""

from __future__ import annotations

import logging
import time
from collections import OrderedDict
from dataclasses import dataclass
from typing import Callable


@dataclass
class _KeyState:
    next_line_at: float  # the key's next line is logged from then on
    held: int = 0        # lines held back since its last one


class RateLimitedLog:
    """``log(level, key, msg, *args)``: at most one line per ``key`` every ``interval_s`` seconds."""

    def __init__(self, logger: logging.Logger, interval_s: float = 10.0, max_keys: int = 256,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self._log = logger
        self.interval_s = float(interval_s)
        self.max_keys = int(max_keys)
        self._clock = clock
        self._keys: OrderedDict[str, _KeyState] = OrderedDict()
        self.suppressed = 0

    def log(self, level: int, key: str, msg: str, *args: object) -> bool:
        """Log ``msg % args`` unless ``key`` had a line less than ``interval_s`` ago; True if it was logged."""
        now = self._clock()
        entry = self._keys.get(key)
        if entry is not None and now < entry.next_line_at:
            entry.held += 1
            self.suppressed += 1
            return False
        held = 0 if entry is None else entry.held
        self._keys[key] = _KeyState(now + self.interval_s)
        self._keys.move_to_end(key)
        while len(self._keys) > self.max_keys:
            self._keys.popitem(last=False)
        if held:
            msg += " (and %d more like it since the last)"
            args = (*args, held)
        self._log.log(level, msg, *args)
        return True

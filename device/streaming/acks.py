"""Acknowledgements that arrive one keyframe at a time, in any order, folded into one contiguous seq."""

from __future__ import annotations


class ContiguousAcks:
    """``acked``: the highest seq acknowledged with every seq before it; an acknowledgement past a gap
    (a keyframe a host could not store) waits in ``above`` until the gap is filled."""

    def __init__(self, acked: int = -1) -> None:
        self.acked = acked
        self.above: set[int] = set()

    def add(self, seq: int) -> bool:
        """Keyframe ``seq`` acknowledged; True when that advanced :attr:`acked`."""
        if seq <= self.acked:
            return False
        self.above.add(seq)
        return self._advance()

    def reset(self, acked: int, keep_above: bool = True) -> None:
        """Everything up to ``acked`` is acknowledged (and nothing past it, unless ``keep_above``)."""
        self.above = {s for s in self.above if s > acked} if keep_above else set()
        self.acked = acked
        self._advance()

    def holds(self, seq: int) -> bool:
        return seq <= self.acked or seq in self.above

    def _advance(self) -> bool:
        before = self.acked
        while self.acked + 1 in self.above:
            self.acked += 1
            self.above.discard(self.acked)
        return self.acked != before

"""Progress bars on stderr (tqdm), shown only where someone watches: the one helper of the host."""

from __future__ import annotations

import sys
from types import TracebackType
from typing import TYPE_CHECKING, Callable

if TYPE_CHECKING:
    from tqdm import tqdm


def progress_bar(total: int, desc: str, enabled: bool | None, unit: str = "it", initial: int = 0) -> tqdm | None:
    """A tqdm bar on stderr, or None (``enabled=None``: only when stderr is a terminal); ``initial``: the
    work done before (a resumed stage's), not counted in the rate and the time left."""
    if enabled is None:
        enabled = sys.stderr.isatty()
    if not enabled:
        return None
    from tqdm import tqdm

    return tqdm(total=total, desc=desc, unit=unit, leave=False, file=sys.stderr, initial=initial)


class Bar:
    """A tqdm bar or nothing, usable as ``with Bar(...) as tick: tick(1)``."""

    def __init__(self, total: int, desc: str, enabled: bool | None, unit: str = "it", initial: int = 0) -> None:
        self.bar = progress_bar(total, desc, enabled, unit, initial)

    def __enter__(self) -> Callable[[int], None]:
        return (lambda n=1: None) if self.bar is None else self.bar.update

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        if self.bar is not None:
            self.bar.close()

"""Log lines for journald: each prefixed with its syslog priority when stderr is the journal."""

from __future__ import annotations

import logging
import os
import sys
from typing import Mapping


class JournalFormatter(logging.Formatter):
    """Prefix each line with its syslog priority (``<3>``) so journald files it at the right level."""

    PRIORITY = {logging.DEBUG: 7, logging.INFO: 6, logging.WARNING: 4, logging.ERROR: 3, logging.CRITICAL: 2}

    def format(self, record: logging.LogRecord) -> str:
        prio = self.PRIORITY.get(record.levelno, 6)
        return f"<{prio}>" + super().format(record).replace("\n", " | ")


def use_journal_format(environ: Mapping[str, str] | None = None) -> bool:
    """When stderr is connected to the journal (``$JOURNAL_STREAM``), tag log lines with priorities."""
    env = os.environ if environ is None else environ
    stream = env.get("JOURNAL_STREAM", "")
    try:
        st = os.fstat(sys.stderr.fileno())
    except (OSError, ValueError, AttributeError):
        return False
    if stream != f"{st.st_dev}:{st.st_ino}":
        return False
    for handler in logging.getLogger().handlers:
        handler.setFormatter(JournalFormatter("%(levelname)s %(name)s: %(message)s"))
    return True

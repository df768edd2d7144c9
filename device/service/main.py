"""``stereopath device run``'s process: load the configuration, route the signals, run one capture session."""

from __future__ import annotations

import logging
import signal
import threading
from pathlib import Path
from types import FrameType
from typing import Callable, Mapping, Union

from stereopath.device.errors import ConfigError
from stereopath.device.service.components import RunSeams
from stereopath.device.service.options import RunOptions, load_config
from stereopath.device.service.sdnotify import Notifier
from stereopath.device.service.service import EXIT_CONFIG, CaptureService

log = logging.getLogger("stereopath.device.service.service")  # one logger name for the service's lines

# what signal.signal returns: a handler, SIG_DFL / SIG_IGN, or None
_Handler = Union[Callable[[int, Union[FrameType, None]], object], int, signal.Handlers, None]


def run_service(config_path: str | Path | None, options: RunOptions | None = None, *,
                environ: Mapping[str, str] | None = None, seams: RunSeams = RunSeams()) -> int:
    """Load the configuration, handle signals (in the main thread) and run one capture session.

    Returns the exit status (0, 1, or 78 for a bad configuration, reported on one log line).
    """
    options = options or RunOptions()
    try:
        cfg = load_config(config_path, options)
    except ConfigError as exc:
        log.error("configuration error: %s", exc)
        Notifier.from_env(environ).notify(STATUS=f"configuration error: {exc}")
        return EXIT_CONFIG
    service = CaptureService(cfg, options, config_path, environ=environ, seams=seams)
    in_main = threading.current_thread() is threading.main_thread()
    previous: dict[int, _Handler] = {}
    if in_main:
        def on_stop(signum: int, _frame: FrameType | None) -> None:
            service.request_stop(f"signal {signal.Signals(signum).name}")

        def on_hup(_signum: int, _frame: FrameType | None) -> None:
            service.request_reload()

        for sig, handler in ((signal.SIGTERM, on_stop), (signal.SIGINT, on_stop), (signal.SIGHUP, on_hup)):
            previous[sig] = signal.signal(sig, handler)
    try:
        return service.run()
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)

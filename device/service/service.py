"""The capture service: ``source -> time align -> estimate -> (record, stream)`` with a systemd lifecycle.

One configuration file (:mod:`stereopath.device.settings`) describes the whole run; the same code path
serves the simulator, a replayed recording and the real cameras.  Threads:

* the **pipeline thread** pulls stereo pairs from the source, drains the IMU, attaches the
  IMU samples to each frame (:class:`~stereopath.device.capture.timealign.TimeAligner`), records the frame, runs
  the estimator, records the pose, publishes it and offers keyframes to the streamer.  The
  recorder writes in fsynced chunks; the streamer's calls never block (its own threads do the
  network), so capture and estimation never wait on a host;
* the **main thread** supervises: readiness, the systemd watchdog, the ~1 Hz health report
  (status file, ``STATUS=`` line, status message), signals, and the orderly stop.

The parts, one module each: :mod:`.options` (command line over file, checks, reload split),
:mod:`.components` (opening the configured backends: the one place that branches on them),
:mod:`.pipeline` (the frame loop), :mod:`.sinks` (recorder and streamer behind one protocol),
:mod:`.watchdog`, :mod:`.status` (health report) and this module (lifecycle and supervision).

Lifecycle (sd_notify, :mod:`stereopath.device.service.sdnotify`):

* ``READY=1`` once the first stereo pair has arrived, the IMU has delivered samples and the
  recorder is open (so a camera or IMU that never starts leaves the unit "activating" and
  systemd's start timeout fails it);
* ``WATCHDOG=1`` every half watchdog period, but only while both a frame and an IMU sample
  arrived within ``service.max_data_age_s`` (capped at half the period): a hung camera or IMU
  stops the pings and systemd restarts the service;
* ``STATUS=`` a one-line health summary each status period;
* SIGTERM/SIGINT: ``STOPPING=1``, the frame in progress finishes, keyframes are spooled (and,
  up to ``stream.drain_s``, acknowledged by a connected host), the recording is flushed and
  its manifest closed: the session on disk is complete and readable;
* SIGHUP: the configuration file is read again; settings that can change live are applied
  (time alignment, recorder reserve, status/watchdog periods, drain time), the others are
  logged as needing a restart.  A bad file is logged and the running configuration kept.

Exit status: 0 after a requested stop or a bounded run, 1 on a runtime failure (camera, IMU,
disk), :data:`EXIT_CONFIG` (78, ``EX_CONFIG``) on a bad configuration, which the unit's
``RestartPreventExitStatus=78`` keeps from restarting in a loop.  Expected faults are logged
as one line without a traceback.

Test seams: ``notifier=``, ``environ=``, ``clock=`` and ``seams=`` (a
:class:`~stereopath.device.service.components.RunSeams`: an unopened stereo source, keyword arguments
for :func:`stereopath.device.capture.sources.create_source` and ``create_imu``, an estimator).
"""

from __future__ import annotations

import json
import logging
import os
import threading
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, Mapping

from stereopath.device.core.config import as_dict
from stereopath.device.errors import ConfigError, StereopathError
from stereopath.device.service.components import Components, RunSeams, open_components
from stereopath.device.service.options import RunOptions, apply_live, check_config, load_config, split_changes
from stereopath.device.service.pipeline import FrameInputs, FramePipeline, PipelineCounters
from stereopath.device.service.sdnotify import Notifier
from stereopath.device.settings import DeviceConfig
from stereopath.device.service.status import StatusReporter, status_line
from stereopath.device.service.watchdog import Watchdog

if TYPE_CHECKING:
    from stereopath.device.capture.timealign import TimeAligner

log = logging.getLogger(__name__)

EXIT_OK, EXIT_FAILURE, EXIT_CONFIG = 0, 1, 78
EXIT_DISK_FULL = 74  # EX_IOERR: the disk filled up during the run (what reached a host is kept there)
TICK_S = 0.05                             # supervisor period


class CaptureService:
    """One capture run (see the module doc).  ``run()`` returns the process exit status."""

    def __init__(self, cfg: DeviceConfig, options: RunOptions | None = None, config_path: str | Path | None = None,
                 *, notifier: Notifier | None = None, environ: Mapping[str, str] | None = None,
                 seams: RunSeams = RunSeams(), clock: Callable[[], float] = time.monotonic) -> None:
        self.cfg = cfg
        self.options = options or RunOptions()
        self.config_path = None if config_path is None else Path(config_path)
        self.environ = os.environ if environ is None else environ
        self.notifier = notifier if notifier is not None else Notifier.from_env(self.environ)
        self._seams = seams
        self._clock = clock
        self.watchdog = Watchdog(self.notifier, self.environ)
        self.parts = Components()           # opened in _setup
        self.counters = PipelineCounters()  # written by the pipeline thread only
        self.pipeline: FramePipeline | None = None
        self._recording_finished = False
        self.session_id = ""
        self.session_dir: Path | None = None
        self._session_dir_existed = True  # set in _setup; a failed start removes only a folder it created
        self.state = "starting"
        self.exit_code = EXIT_OK
        self.stop_reason = ""
        self.ready_at: float | None = None
        self._stop = threading.Event()
        self._reload = threading.Event()
        self._wake = threading.Event()
        self._thread: threading.Thread | None = None
        self.reporter = StatusReporter(clock)
        self.last_status: dict[str, Any] = {}  # the latest report written
        self._client_keys_at_start: dict[str, bytes] = {}

    # ------------------------------------------------------------------ what tests and the status read

    @property
    def ready(self) -> bool:
        return self.ready_at is not None

    @property
    def frames_in(self) -> int:
        return self.counters.frames_in

    @property
    def keyframes(self) -> int:
        return self.counters.keyframes

    @property
    def last_frame_at(self) -> float | None:
        return self.counters.last_frame_at

    @property
    def last_imu_at(self) -> float | None:
        return self.counters.last_imu_at

    @property
    def aligner(self) -> TimeAligner | None:
        return self.parts.aligner

    # ------------------------------------------------------------------ control (any thread, signal handlers)

    def request_stop(self, reason: str = "stop requested") -> None:
        if not self._stop.is_set():
            self.stop_reason = self.stop_reason or reason
            self._stop.set()
        self._wake.set()

    def request_reload(self) -> None:
        self._reload.set()
        self._wake.set()

    # ------------------------------------------------------------------ run

    def run(self) -> int:
        logging.getLogger().addHandler(self.reporter.problem)
        try:
            return self._run()
        finally:
            logging.getLogger().removeHandler(self.reporter.problem)
            self.notifier.close()

    def _run(self) -> int:
        self.reporter.path = Path(self.cfg.service.status_file) if self.cfg.service.status_file else None
        self.notifier.notify(STATUS="starting: opening the cameras, the IMU and the recorder")
        try:
            self._setup()
        except ConfigError as exc:
            log.error("configuration error: %s", exc)
            self._fail_start("configuration error", exc, EXIT_CONFIG)
            return self.exit_code
        except StereopathError as exc:
            log.error("cannot start: %s", exc)
            self._fail_start("failed to start", exc, EXIT_FAILURE)
            return self.exit_code
        except BaseException:
            self._teardown()
            raise
        self._wait_for_host()
        pipeline = self.pipeline
        assert pipeline is not None
        self._thread = threading.Thread(target=pipeline.run, args=(self._wake.set,), name="stereopath-pipeline",
                                        daemon=True)
        started = self._clock()
        self._thread.start()
        self._supervise(started)
        self._shutdown()
        return self.exit_code

    def _fail_start(self, what: str, exc: BaseException, code: int) -> None:
        self.exit_code = code
        self.state = "failed"
        self.notifier.notify(STATUS=f"{what}: {exc}")
        self._teardown()
        self._write_status(final=True)
        if self.session_dir is not None and not self._session_dir_existed:
            from stereopath.device.formats.session_cleanup import discard_unused_session

            discard_unused_session(self.session_dir)

    # ------------------------------------------------------------------ set-up

    def _setup(self) -> None:
        from stereopath.device.wire.protocol import new_session_id

        cfg = self.cfg
        check_config(cfg, self.environ)
        log.info("configuration%s: %s", f" from {self.config_path}" if self.config_path else " (built-in defaults)",
                 json.dumps(as_dict(cfg), separators=(",", ":"), default=str))
        self.session_id = new_session_id()
        self.session_dir = Path(self.options.out) if self.options.out else Path(cfg.recorder.dir) / self.session_id
        from stereopath.device.formats.fileio import check_out_folder

        # never the root, a recorded session or a folder of one; nor a file or a folder that cannot be written
        check_out_folder(self.session_dir, option="--out" if self.options.out else "recorder.dir/<session id>")
        self._session_dir_existed = self.session_dir.exists()
        if self.session_dir.exists() and (not self.session_dir.is_dir() or any(self.session_dir.iterdir())):
            raise ConfigError(f"--out {self.session_dir}: exists and is not empty (a session is never overwritten; "
                              f"name a new folder: keyframes of earlier sessions in {self.session_dir.parent} or "
                              f"recorder.dir that no host acknowledged are offered to hosts again)")
        p = open_components(cfg, self.session_dir, self.session_id, seams=self._seams, environ=self.environ,
                            parts=self.parts)
        self.pipeline = FramePipeline(FrameInputs(p.source, p.imu, p.aligner, p.estimator),
                                      [s for s in (p.recording, p.streaming) if s.active],
                                      stop=self._stop, request_stop=self.request_stop,
                                      frame_limit=self.options.frames, clock=self._clock, counters=self.counters)
        self._client_keys_at_start = self._client_keys()
        self.state = "waiting"
        self._write_status()

    def _client_keys(self) -> dict[str, bytes]:
        """The authorised host keys (read at start by the streamer's authenticator)."""
        d = Path(self.cfg.keys.clients_dir)
        try:
            return {p.name: p.read_bytes() for p in sorted(d.glob("*.key"))}
        except OSError:
            return {}

    def _wait_for_host(self) -> None:
        """``--wait-for-host``: hold capture until a host has said hello, so it sees every pose."""
        streaming, limit = self.parts.streaming, self.options.wait_for_host_s
        if not streaming.active or limit <= 0:
            return
        self.notifier.notify(STATUS="waiting for a host to connect")
        deadline = self._clock() + limit
        while not self._stop.is_set() and self._clock() < deadline:
            stats = streaming.stats()
            # a host has said hello on the keyframe channel and its pose subscription has reached the
            # publisher (the XPUB hands it up): the first pose published now reaches it
            if any(p.get("connected") for p in stats.get("peers", [])) and stats.get("pose_subscriptions", 0) > 0:
                log.info("a host is connected and subscribed to poses; starting capture")
                return
            self._stop.wait(0.05)
        if not self._stop.is_set():
            log.warning("no host connected within %g s; capturing anyway", limit)

    # ------------------------------------------------------------------ supervisor (main thread)

    def max_data_age_s(self) -> float:
        return self.watchdog.max_data_age_s(self.cfg.service.max_data_age_s)

    def data_fresh(self, now: float) -> bool:
        """A frame and (when an IMU is configured) an IMU sample arrived within the allowed age."""
        c = self.counters
        return self.watchdog.data_fresh(now, self.max_data_age_s(), c.last_frame_at, c.last_imu_at,
                                        self.parts.imu is not None)

    def _supervise(self, started: float) -> None:
        next_status = started
        while True:
            self._wake.wait(TICK_S)
            self._wake.clear()
            now = self._clock()
            if self._reload.is_set():
                self._reload.clear()
                self._do_reload()
            if not self.ready and self._sensors_started():
                self._become_ready(now)
                next_status = now
            self._check_pipeline()
            if self._stop.is_set():
                return
            if not self.ready:
                if now - started > self.cfg.service.ready_timeout_s:
                    self._fail(StereopathError(f"not ready after {self.cfg.service.ready_timeout_s:g} s: "
                                               f"{self._missing_sensor()}"))
                    return
            else:
                self.watchdog.tick(now, self.data_fresh(now))
                if self.options.duration_s is not None and now - self.ready_at >= self.options.duration_s:
                    self.request_stop(f"{self.options.duration_s:g} s elapsed")
                    return
            if now >= next_status:
                status = self._write_status()
                if self.ready:
                    self.notifier.notify(STATUS=status_line(status))
                next_status = now + self.cfg.service.status_interval_s

    def _sensors_started(self) -> bool:
        c, failure = self.counters, self.pipeline.failure if self.pipeline else None
        return failure is None and c.last_frame_at is not None and (self.parts.imu is None or
                                                                    c.last_imu_at is not None)

    def _missing_sensor(self) -> str:
        if self.counters.last_frame_at is None:
            return f"no stereo pair from the {self.cfg.source.backend} source"
        return f"no samples from the {self.cfg.imu.backend} IMU"

    def _check_pipeline(self) -> None:
        p = self.pipeline
        if p is None or not p.done.is_set():
            return
        if p.failure is not None:
            self._fail(p.failure)
        elif not self._stop.is_set():
            self.request_stop("the pipeline ended")

    def _become_ready(self, now: float) -> None:
        self.ready_at = now
        self.reporter.cpu.restart()
        self.state = "running"
        status = self._write_status()
        self.notifier.notify(READY=1, STATUS=status_line(status))
        endpoints = ""
        st = self.parts.streaming
        if st.active:
            endpoints = f"; streaming on {st.pose_endpoint} and {st.keyframe_endpoint}"
        log.info("ready: session %s in %s%s", self.session_id, self.session_dir, endpoints)

    def _fail(self, exc: BaseException) -> None:
        if isinstance(exc, StereopathError):
            log.error("stopping: %s", exc)
        self.exit_code = EXIT_FAILURE
        self.state = "failed"
        self.request_stop(f"failure: {exc}")

    def _do_reload(self) -> None:
        if self.config_path is None:
            log.warning("SIGHUP: no configuration file to reload (started with built-in defaults)")
            return
        self.notifier.notify(RELOADING=1, MONOTONIC_USEC=time.monotonic_ns() // 1000)
        try:
            new = load_config(self.config_path, self.options)
            check_config(new, self.environ)
        except ConfigError as exc:
            log.error("reload of %s failed, keeping the running configuration: %s", self.config_path, exc)
            self.notifier.notify(READY=1)
            return
        live, restart = split_changes(self.cfg, new)
        if self.parts.streaming.active and not self.cfg.stream.insecure \
                and self._client_keys() != self._client_keys_at_start:
            restart.append(f"host keys in {new.keys.clients_dir}")
        if live:
            if any(k.startswith("timealign.") for k in live) and self.pipeline is not None:
                self.pipeline.set_timealign(new.timealign)
            if "recorder.reserve_mb" in live:
                self.parts.recording.set_reserve_bytes(int(new.recorder.reserve_mb * 1e6))
            self.cfg = apply_live(self.cfg, new)
        log.info("configuration reloaded from %s: applied %s%s", self.config_path,
                 ", ".join(live) or "nothing",
                 f"; needs a restart: {', '.join(restart)}" if restart else "")
        self.notifier.notify(READY=1)

    # ------------------------------------------------------------------ stop

    def _shutdown(self) -> None:
        self.notifier.notify(STOPPING=1, STATUS=f"stopping: {self.stop_reason}")
        log.info("stopping: %s", self.stop_reason)
        self._say_which_sensor_went_quiet()
        if self.state != "failed":
            self.state = "stopping"
        self._write_status()
        self._join_pipeline()
        failure = self.pipeline.failure if self.pipeline is not None else None
        if failure is not None and self.exit_code == EXIT_OK:
            self._fail(failure)
        self._finish_recording()  # before the drain, which may wait for hosts: a kill then loses nothing recorded
        self.parts.streaming.drain(self.cfg.stream.drain_s, self._clock)
        self._report_disk_full()
        self._teardown()
        if self.state != "failed":
            self.state = "stopped"
        self._write_status(final=True)
        c = self.counters
        log.info("session %s ended (%s): %d frames in, %d estimated, %d keyframes, recorder %s", self.session_id,
                 self.stop_reason, c.frames_in, c.frames_done, c.keyframes, self.parts.recording.state)

    def _finish_recording(self) -> None:
        """Ground truth, estimator summary, then the recording closed (rows flushed, manifest final); once."""
        if self._recording_finished:
            return
        self._recording_finished = True
        p = self.parts
        try:  # the extras first; a failure there must not keep the recording from being closed
            p.recording.write_groundtruth(getattr(getattr(p.source, "session", None), "groundtruth", None))
            summary = self.pipeline.estimator_summary() if self.pipeline is not None else None
            if summary is not None:
                p.recording.write_json("estimator.json", summary)
        except StereopathError as exc:
            log.error("writing the recording's ground truth or estimator summary: %s", exc)
        try:
            p.recording.close()
        except StereopathError as exc:
            log.error("closing the recording: %s", exc)
            self.exit_code = self.exit_code or EXIT_FAILURE

    def _report_disk_full(self) -> None:
        """A disk that filled up during the run is said once at the end, with what it cost, and exits 74."""
        rec_state = getattr(self.parts.recording, "state", "off")
        f = self.parts.streaming.status_fields()
        if rec_state != "stopped_low_disk" and not f.get("spool_disk_full"):
            return
        msg = (f"disk full: recording {rec_state}; {f.get('keyframes_in_memory_unacked', 0)} keyframe(s) held in "
               f"memory were not acknowledged by a host (lost now), {f.get('keyframes_failed', 0)} could not be kept")
        log.error("%s", msg)
        self.notifier.notify(STATUS=msg)
        if self.exit_code == EXIT_OK:
            self.exit_code = EXIT_DISK_FULL

    def _say_which_sensor_went_quiet(self) -> None:
        """E.g. after the watchdog's SIGTERM: log which sensor stopped delivering."""
        now = self._clock()
        if not self.ready or self.data_fresh(now):
            return
        c = self.counters
        ages = {"frame": c.last_frame_at, "IMU sample": c.last_imu_at if self.parts.imu is not None else now}
        quiet = [f"no {k} for {now - t:.1f} s" for k, t in ages.items() if t is not None and
                 now - t > self.max_data_age_s()]
        if quiet:
            log.warning("sensor data stopped before the stop request: %s", ", ".join(quiet))

    def _join_pipeline(self) -> None:
        thread = self._thread
        stop_timeout = self.cfg.service.stop_timeout_s
        if thread is None:
            return
        thread.join(min(2.0, stop_timeout))
        if thread.is_alive():  # blocked in the source: closing it unblocks the iterator
            self._close_source()
            thread.join(stop_timeout)
        if thread.is_alive():
            log.error("the pipeline did not stop within %.0f s (camera or IMU hung); closing the session anyway",
                      stop_timeout)

    def _close_source(self) -> None:
        src = self.parts.source
        if src is None:
            return
        try:
            src.close()
        except StereopathError as exc:
            log.warning("closing the source: %s", exc)

    def _teardown(self) -> None:
        """Close everything that was opened, in reverse order; each step is independent."""
        p = self.parts
        p.streaming.close()
        self._finish_recording()
        close = getattr(p.estimator, "close", None)
        if close is not None:
            close()
        if p.imu is not None:
            try:
                p.imu.close()
            except StereopathError as exc:
                log.warning("closing the IMU: %s", exc)
        self._close_source()

    # ------------------------------------------------------------------ status

    def status(self) -> dict[str, Any]:
        """The health report (written to the status file each period)."""
        return self.reporter.report(self)

    def _write_status(self, final: bool = False) -> dict[str, Any]:
        data = self.status()
        self.last_status = data
        if not final:
            self.parts.streaming.publish_health(data)
        self.reporter.write(data)
        return data

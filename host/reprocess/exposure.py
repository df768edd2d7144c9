"""The recorded right images in the left camera's grey levels, for the offline stages (tracks, ba, map).

Two cameras that set their exposure independently record the same surface at different grey levels,
and every right-image search that assumes equal brightness loses matches.  The on-board estimator
corrects this as it runs (``StereoConfig.match_exposure``); :class:`ExposureMatchedSequence` does the
same for a recorded session: ``left ~ gain * right + offset`` (:mod:`stereopath.device.core.photometric`)
fitted on every ``stride``-th frame, each frame using the median of the ``span`` nearest fits and
corrected only above ``tolerance`` grey levels.  The fits depend on the images only, so every stage,
process and Ray worker sees the same frames.  See docs/architecture.md, "Two cameras, two exposures".
"""

from __future__ import annotations

import dataclasses
import logging
from collections import OrderedDict
from typing import Any

import cv2
import numpy as np

from stereopath.device.core.features import gray
from stereopath.device.core.frames import StereoFrame
from stereopath.device.core.photometric import GainOffset, correct_right, measure_relation, relation_matters
from stereopath.device.core.stereo import stereo_right, undistort_px
from stereopath.device.errors import ConfigError, DatasetError
from stereopath.device.formats.sequence import SequenceBase

log = logging.getLogger(__name__)

PROBE_CORNERS = 300
PROBE_QUALITY = 0.01
PROBE_SPACING_PX = 12


def probe_relation(rig, left: np.ndarray, right: np.ndarray, cfg) -> GainOffset | None:
    """The grey-level relation of one recorded pair: left-image corners searched in the right image by
    stereo KLT (``cfg``: a :class:`~stereopath.host.backend.tracks.TrackConfig`, its KLT settings
    and depth guess), measured by :func:`~stereopath.device.core.photometric.measure_relation`;
    None when not identifiable."""
    from stereopath.host.backend.tracks import right_guess_at_depth

    left, right = gray(left), gray(right)
    c = cv2.goodFeaturesToTrack(left, maxCorners=PROBE_CORNERS, qualityLevel=PROBE_QUALITY,
                                minDistance=PROBE_SPACING_PX)
    if c is None:
        return None
    xy = c.reshape(-1, 2).astype(np.float32)
    guess = right_guess_at_depth(rig, undistort_px(xy, rig.cam0.K, rig.cam0.dist), cfg)
    return measure_relation(left, right, xy, lambda image: stereo_right(rig, left, image, xy, guess, cfg.stereo))


class ExposureMatchedSequence(SequenceBase):
    """``seq`` with each right image corrected to the left camera's grey levels where they differ
    (see the module doc).  Everything else (rig, times, IMU, ground truth, the unreadable frames met
    so far) is ``seq``'s own; ``relation(i)`` is what frame ``i`` was corrected with (None: as recorded)."""

    def __init__(self, seq: Any, cfg: Any, tolerance: float = 4.0, stride: int = 2, span: int = 5) -> None:
        if stride < 1 or span < 1:
            raise ConfigError(f"exposure matching: stride and span must be >= 1 (got {stride}, {span})")
        self.inner, self.cfg, self.tolerance, self.stride, self.span = seq, cfg, float(tolerance), int(stride), int(span)
        self.name = getattr(seq, "name", "sequence")
        self.spec = getattr(seq, "spec", "")
        self._fits: dict[int, GainOffset | None] = {}
        # the last frames read as recorded: a fit reads the grid frames ahead of the one asked for, and a
        # stage going through the frames in order asks for those next (read once, not twice)
        self._recent: OrderedDict[int, StereoFrame] = OrderedDict()
        self._keep = self.stride * self.span + 1  # the farthest a fit reads ahead, plus the frame itself

    # the inner sequence's state, shared rather than copied
    rig = property(lambda self: self.inner.rig)
    t_ns = property(lambda self: self.inner.t_ns)
    imu = property(lambda self: self.inner.imu)
    groundtruth = property(lambda self: self.inner.groundtruth)
    skipped_frames = property(lambda self: self.inner.skipped_frames)

    @property
    def strict(self) -> bool:
        return self.inner.strict

    @strict.setter
    def strict(self, value: bool) -> None:  # unreadable frames: skipped (False) or stop the run (True)
        self.inner.strict = value

    def __len__(self) -> int:
        return len(self.inner)

    def __getattr__(self, name: str) -> Any:  # anything else a source offers (trajectory, session folder ...)
        if name == "inner":
            raise AttributeError(name)
        return getattr(self.inner, name)

    def _fit(self, g: int, frame: StereoFrame | None = None) -> GainOffset | None:
        """The fit at grid frame ``g`` (cached; None when unreadable or not identifiable); ``frame``: that
        frame when the caller has read it already."""
        if g not in self._fits:
            try:
                fr = frame if frame is not None else self._recorded(g)
            except DatasetError as exc:
                log.warning("%s: exposure probe skips unreadable frame %d: %s", self.name, g, exc)
                self._fits[g] = None
            else:
                self._fits[g] = probe_relation(self.rig, fr.left, fr.right, self.cfg)
        return self._fits[g]

    def measured(self, i: int) -> GainOffset | None:
        """The median of the fits at the ``span`` grid frames nearest to frame ``i`` (None: none identifiable)."""
        grid = np.arange(0, len(self), self.stride)
        near = np.sort(grid[np.argsort(np.abs(grid - i), kind="stable")[: self.span]])
        fits = [f for f in (self._fit(int(g)) for g in near) if f is not None]
        if not fits:
            return None
        med = np.median([(f.gain, f.offset, f.change) for f in fits], axis=0)
        return GainOffset(float(med[0]), float(med[1]), sum(f.n for f in fits), float(med[2]))

    def relation(self, i: int) -> GainOffset | None:
        """What frame ``i`` is corrected with: :meth:`measured`, or None when it changes the matched
        texture by no more than ``tolerance`` grey levels (the frame as recorded)."""
        rel = self.measured(i)
        return rel if relation_matters(rel, self.tolerance) else None

    def _recorded(self, i: int) -> StereoFrame:
        """Frame ``i`` as recorded (the last ``stride * span + 1`` frames read are kept: 11 by default, 8 MB
        of 752 x 480 pairs)."""
        fr = self._recent.pop(i, None)
        if fr is None:
            fr = self.inner.frame(i)
            for image in (fr.left, fr.right):  # shared by whoever asks for the frame next: not to be changed
                if isinstance(image, np.ndarray):
                    image.flags.writeable = False
        self._recent[i] = fr
        while len(self._recent) > self._keep:
            self._recent.popitem(last=False)
        return fr

    def frame_as_recorded(self, i: int) -> StereoFrame:
        """Frame ``i`` without the correction (nothing is fitted for it): for a stage that reads only
        its left image, which the correction leaves as it is."""
        n = len(self)
        if not -n <= i < n:
            raise IndexError(f"{self.name}: frame {i} out of range (0..{n - 1})")
        return self._recorded(i % n)

    def _load(self, i: int) -> StereoFrame:
        fr = self._recorded(i)
        if i % self.stride == 0:  # a grid frame: fitted on the images just read, not read again
            self._fit(i, fr)
        rel = self.relation(i)
        if rel is None:
            return fr
        return dataclasses.replace(fr, right=correct_right(fr.right, rel))

    def summary(self, frames: np.ndarray) -> dict[str, Any]:
        """For a stage's statistics: of ``frames`` (indices), how many are corrected, and the median of
        their measured relations (it depends on the images only, not on what was read before)."""
        rels = [r for r in (self.measured(int(i)) for i in frames) if r is not None]
        out: dict[str, Any] = {"frames": len(frames), "measured": len(rels),
                               "corrected": sum(relation_matters(r, self.tolerance) for r in rels)}
        if rels:
            med = np.median([(r.gain, r.offset, r.change) for r in rels], axis=0)
            out.update(gain=round(float(med[0]), 4), offset=round(float(med[1]), 2), change=round(float(med[2]), 2))
        return out

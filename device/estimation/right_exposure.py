"""The right camera's grey levels against the left's, followed on line: fits on stereo matches, their
running median, and the correction applied to the right image while it matters."""

from __future__ import annotations

import numpy as np

from stereopath.device.core.photometric import GainOffset, correct_right, fit_gain_offset, relation_matters
from stereopath.device.estimation.live_state import StereoStats

FITS_KEPT = 5  # one fit is noisy: the median of the last five, a quarter of a second at 20 Hz


class RightExposure:
    """The relation in use (None: the cameras agree within ``tolerance``) and the last fits."""

    def __init__(self, tolerance: float, counts: StereoStats) -> None:
        self.tolerance = tolerance
        self.counts = counts
        self.relation: GainOffset | None = None
        self.fits: list[GainOffset] = []

    def corrected(self, right: np.ndarray) -> np.ndarray:
        """``right`` in the left camera's grey levels when the two cameras differ."""
        if self.relation is None:
            return right
        self.counts.exposure_corrected_frames += 1
        return correct_right(right, self.relation)

    def fit(self, left: np.ndarray, right_raw: np.ndarray, xy_left: np.ndarray, xy_right: np.ndarray) -> None:
        """Re-measure the right camera's grey levels against the left's on these stereo matches; the
        correction is used from the next frame if it matters, dropped if it no longer does, kept if these
        matches do not identify it."""
        self.take(fit_gain_offset(left, right_raw, xy_left, xy_right))

    def take(self, rel: GainOffset | None) -> None:
        """Take one fit into the median of the last ones; None (not identifiable) changes nothing."""
        if rel is None:
            return
        # a fit at every tracked frame (the pose solve's right-image matches) and one at each keyframe, so
        # two AGCs that disagree from moment to moment are followed; fits at keyframes alone would lag
        self.fits = (self.fits + [rel])[-FITS_KEPT:]
        med = np.median([(f.gain, f.offset, f.change) for f in self.fits], axis=0)
        rel = GainOffset(float(med[0]), float(med[1]), rel.n, float(med[2]))
        self.counts.exposure_fits += 1
        self.counts.right_gain_milli = int(round(1000 * rel.gain))
        self.counts.right_offset_centi = int(round(100 * rel.offset))
        self.relation = rel if relation_matters(rel, self.tolerance) else None

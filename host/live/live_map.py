"""Live incremental mapping for ``stereopath host live --map``.

Keyframes handed over by the receiver thread are fused on a worker thread (depth + TSDF), so receiving
never waits on mapping.  Every ``every`` keyframes the mesh is written to ``OUT/<session>/model/mesh.ply``
(atomically) and shown in rerun; at the end each session's whole model is written.  With ``loops`` (on
by default) a closed loop (:class:`stereopath.host.live.live_loops.LiveLoopCloser`) re-poses every fused
keyframe and re-integrates the TSDF from the kept depth maps, and the mesh is refreshed at once.  Each
session is mapped with the rig its keyframes were taken with: the device's own (``rig_for``), else the
given ``rig`` when its hash matches; a given rig that differs from the device's is named in one warning.
A device that redefines its world during the session (a start in motion, levelled once gravity is known:
:class:`~stereopath.device.wire.messages.WorldRebase`, handed over by the receiver through
:meth:`LiveMapper.on_rebase`) has the keyframes fused before it moved into the new world: their poses
(and the loop closer's) are mapped and the TSDF is integrated again from the kept depth maps, so the
model stays in one world; the depth maps are kept for that whether loops are on or not.
See docs/architecture.md, "A keyframe on the host".
"""

from __future__ import annotations

import logging
import queue
import threading
from pathlib import Path
from typing import TYPE_CHECKING, Callable

import numpy as np

from stereopath.device.errors import CalibrationError, StereopathError
from stereopath.device.core.rig import Rig
from stereopath.device.wire.messages import WorldRebase
from stereopath.device.wire.protocol import Keyframe

if TYPE_CHECKING:
    import open3d as o3d

    from stereopath.host.backend.loops import LoopConfig
    from stereopath.host.live.live_loops import LiveLoopCloser
    from stereopath.host.mapping.mapper import DenseMapper

log = logging.getLogger(__name__)


class LiveMapper:
    def __init__(self, rig: Rig | None, out_dir: str | Path, every: int = 10, preset: str = "object",
                 on_mesh: Callable[[str, o3d.geometry.TriangleMesh], None] | None = None,
                 rig_for: Callable[[str], Rig | None] | None = None, loops: bool | LoopConfig | None = True) -> None:
        from stereopath.device.wire.protocol import rig_reference

        self.rig = rig
        self.rig_for = rig_for
        self._session_rigs: dict[str, Rig] = {}
        self.out = Path(out_dir)
        self.every = max(1, int(every))
        self.preset = preset
        self.on_mesh = on_mesh
        self._ref = rig_reference(rig) if rig is not None else None
        self._mappers: dict[str, DenseMapper] = {}
        # loops: True (default LoopConfig), False/None (off) or a LoopConfig
        self.loops = loops
        self._closers: dict[str, LiveLoopCloser] = {}
        self.loops_closed = 0
        self._fused_t: dict[str, list[int]] = {}  # each session's fused keyframes' times, in the mapper's order
        self._q: queue.Queue[Keyframe | WorldRebase | None] = queue.Queue()
        self._thread = threading.Thread(target=self._work, name="live-map", daemon=True)
        self._thread.start()
        self.rejected = 0
        self.fused = 0
        self.refreshes = 0
        self.rebased = 0  # world rebases applied to a model

    def on_keyframe(self, kf: Keyframe, new: bool) -> None:
        if new:
            self._q.put(kf)

    def on_rebase(self, msg: WorldRebase) -> None:
        """A session's world redefined (the receiver applies each rebase once): the keyframes fused from
        before it are moved into the new world, in turn with the keyframes handed over around it."""
        self._q.put(msg)

    def _rig_of(self, kf: Keyframe) -> Rig:
        """The rig ``kf`` was taken with: the device's (stored from its session message), else ``rig``."""
        from stereopath.device.wire.protocol import rig_reference

        rig = self._session_rigs.get(kf.session_id)
        if rig is None:
            device = self.rig_for(kf.session_id) if self.rig_for is not None else None
            if device is not None and rig_reference(device)[1] == kf.rig_hash:
                if self._ref is not None and self._ref[1] != kf.rig_hash:
                    log.warning("live map: --rig %s (%s) is not the rig session %s was taken with; mapping with "
                                "the device's rig %s (%s)", self._ref[0], self._ref[1], kf.session_id,
                                kf.rig_name, kf.rig_hash)
                rig = device
            elif self.rig is not None and self._ref is not None and self._ref[1] == kf.rig_hash:
                rig = self.rig
            else:
                given = f"; --rig is {self._ref[0]} ({self._ref[1]})" if self._ref is not None else ""
                raise CalibrationError(f"keyframe {kf.seq} of session {kf.session_id} was taken with rig "
                                       f"{kf.rig_name} ({kf.rig_hash}) and the device sent no calibration for it{given}")
            self._session_rigs[kf.session_id] = rig
        elif rig_reference(rig)[1] != kf.rig_hash:
            raise CalibrationError(f"keyframe {kf.seq} of session {kf.session_id} names rig {kf.rig_name} "
                                   f"({kf.rig_hash}), not the session's")
        return rig

    def _mapper(self, session: str, rig: Rig) -> DenseMapper:
        from stereopath.host.mapping.mapper import DenseMapper, map_preset

        if session not in self._mappers:
            # the depth maps are kept for a loop's or a world rebase's re-integration
            self._mappers[session] = DenseMapper(rig, map_preset(self.preset), source=f"live:{session}",
                                                 keep_depth=True)
        return self._mappers[session]

    def _fuse(self, kf: Keyframe, rig: Rig) -> bool:
        """Fuse one keyframe (at its loop-corrected pose); True when it closed a loop and the map was re-posed."""
        from stereopath.device.wire.protocol import decode_image
        from stereopath.host.live.live_loops import LiveLoopCloser

        m = self._mapper(kf.session_id, rig)
        left, right = decode_image(kf.left), decode_image(kf.right)
        if not self.loops:
            m.add(left, right, kf.T_world_cam, kf.seq)
            self._fused_t.setdefault(kf.session_id, []).append(int(kf.t_ns))
            return False
        closer = self._closers.get(kf.session_id)
        if closer is None:
            closer = self._closers[kf.session_id] = LiveLoopCloser(rig, None if self.loops is True else self.loops)
        closed = closer.add(left, right, kf.T_world_cam)
        T = closer.poses()
        try:
            m.add(left, right, T[-1], kf.seq)
        except StereopathError:
            closer.discard_last()  # the map and the closer keep the same keyframes
            raise
        self._fused_t.setdefault(kf.session_id, []).append(int(kf.t_ns))
        if closed:
            m.repose(T)
            self.loops_closed += 1
        return closed

    def _work(self) -> None:
        while True:
            kf = self._q.get()
            if kf is None:
                return
            if isinstance(kf, WorldRebase):
                self._rebase(kf)
                continue
            try:
                rig = self._rig_of(kf)
                closed = self._fuse(kf, rig)
                m = self._mapper(kf.session_id, rig)
                self.fused += 1
            except StereopathError as exc:
                self.rejected += 1
                log.warning("live map: keyframe %s not fused: %s", getattr(kf, "seq", "?"), exc)
                continue
            if m.keyframes % self.every == 0 or closed:  # a closed loop is shown at once
                self._refresh(kf.session_id, m)

    def _refresh(self, session: str, m: DenseMapper) -> None:
        """The session's mesh written and shown (nothing while no surface has enough views)."""
        from stereopath.host.mapping.fusion import write_mesh

        mesh = m.mesh()
        if len(mesh.triangles) == 0:
            return
        path = self.out / session / "model" / "mesh.ply"
        path.parent.mkdir(parents=True, exist_ok=True)
        write_mesh(mesh, path)
        self.refreshes += 1
        if self.on_mesh is not None:
            self.on_mesh(session, mesh)

    def _rebase(self, msg: WorldRebase) -> None:
        """The keyframes of ``msg``'s session fused before ``from_t_ns`` moved by ``T_new_old`` (see the module
        doc); the mesh shown again at once."""
        m = self._mappers.get(msg.session_id)
        times = self._fused_t.get(msg.session_id, [])
        moved = np.array([t < msg.from_t_ns for t in times], bool)
        if m is None or not moved.any():
            return
        A = msg.T_new_old
        closer = self._closers.get(msg.session_id)
        if closer is not None:
            closer.rebase(A, moved)
            T = closer.poses()
        else:
            T = np.array([A @ Tk if mv else Tk for Tk, mv in zip(m.poses, moved)])
        try:
            m.repose(T)
        except StereopathError as exc:
            log.error("live map: session %s's model not moved into the rebased world: %s", msg.session_id, exc)
            return
        self.rebased += 1
        log.info("live map: session %s's world rebased: %d fused keyframes moved", msg.session_id, int(moved.sum()))
        self._refresh(msg.session_id, m)

    def close(self) -> dict[str, Path]:
        """Finish the worker and write each session's full model; returns the model folders."""
        from stereopath.host.mapping.mapper import write_map

        self._q.put(None)
        self._thread.join()
        out = {}
        for session, m in self._mappers.items():
            if m.keyframes == 0:
                continue
            try:
                write_map(m.finish(), self.out / session / "model")
                out[session] = self.out / session / "model"
            except StereopathError as exc:
                log.warning("live map of session %s not written: %s", session, exc)
        return out

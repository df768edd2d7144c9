"""host live --map: keyframes fused as they arrive, mesh refreshed, full model at the end."""

import numpy as np
import pytest

from stereopath.device.core.geometry import matrix_to_quat_xyzw
from stereopath.device.wire.protocol import Keyframe, decode_keyframe, encode_image, encode_keyframe, rig_reference
from stereopath.device.core.rig import paper_rig
from stereopath.host.live.live_map import LiveMapper
from stereopath.device.formats.source import open_source


def _keyframes(seq, rig, step=4, n=6, session="s1"):
    name, h = rig_reference(rig)
    out = []
    for k, i in enumerate(range(30, 30 + step * n, step)):
        f = seq.render(i)
        T = f.meta["T_world_cam0"]
        kf = Keyframe(session, k, i, f.t_ns, tuple(T[:3, 3]), tuple(matrix_to_quat_xyzw(T[:3, :3])),
                      encode_image(f.left, "png"), encode_image(f.right, "png"), name, h)
        out.append(decode_keyframe(encode_keyframe(kf)))  # exactly what the receiver hands over
    return out


def test_live_mapper_fuses_refreshes_and_writes_the_model(tmp_path):
    seq = open_source("sim:0", frames=60)
    kfs = _keyframes(seq, seq.rig)
    refreshed = []
    m = LiveMapper(seq.rig, tmp_path, every=2, on_mesh=lambda s, mesh: refreshed.append(len(mesh.vertices)))
    for kf in kfs:
        m.on_keyframe(kf, True)
    m.on_keyframe(kfs[0], False)  # a duplicate is not fused twice
    models = m.close()
    assert m.fused == 6 and m.rejected == 0
    assert m.refreshes == len(refreshed) >= 1 and min(refreshed) > 1000
    assert refreshed == sorted(refreshed)  # the model grows as keyframes arrive
    model = models["s1"]
    for name in ("mesh.ply", "cloud.ply", "model.png", "map.json"):
        assert (model / name).stat().st_size > 0


def test_live_mapper_rejects_keyframes_of_another_rig(tmp_path):
    seq = open_source("sim:0", frames=40)
    kfs = _keyframes(seq, paper_rig(), n=2)  # the rig without the IMU extrinsics: another hash
    m = LiveMapper(seq.rig, tmp_path, every=1)
    for kf in kfs:
        m.on_keyframe(kf, True)
    assert m.close() == {}
    assert m.rejected == 2 and m.fused == 0
    assert not (tmp_path / "s1").exists()

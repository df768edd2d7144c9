import numpy as np
import pytest

from stereopath.device.core.geometry import (
    chordal_mean, euler_xyz_to_matrix, invert_pose, make_pose, matrix_to_euler_xyz,
    matrix_to_quat_xyzw, project_to_so3, quat_xyzw_to_matrix, rot_x, rot_y, rot_z,
    rotation_angle_deg, so3_exp, so3_log,
)

rng = np.random.default_rng(1)


def random_rotation():
    return so3_exp(rng.normal(size=3))


def test_exp_log_round_trip():
    for _ in range(50):
        w = rng.normal(size=3)
        w *= min(1.0, 3.0 / np.linalg.norm(w))
        assert np.allclose(so3_log(so3_exp(w)), w, atol=1e-9)
    # near pi
    w = np.array([0.0, 0.0, np.pi - 1e-6])
    assert np.allclose(so3_exp(so3_log(so3_exp(w))), so3_exp(w), atol=1e-6)


def test_euler_xyz_is_rx_ry_rz():
    a, b, c = 0.3, -0.2, 0.7
    assert np.allclose(euler_xyz_to_matrix([a, b, c]), rot_x(a) @ rot_y(b) @ rot_z(c))
    assert np.allclose(matrix_to_euler_xyz(rot_x(a) @ rot_y(b) @ rot_z(c)), [a, b, c])


def test_quaternion_round_trip_and_convention():
    for _ in range(50):
        R = random_rotation()
        q = matrix_to_quat_xyzw(R)
        assert q[3] >= 0 and np.isclose(np.linalg.norm(q), 1)
        assert np.allclose(quat_xyzw_to_matrix(q), R, atol=1e-12)
    # 90 deg about z: (0, 0, sin45, cos45)
    assert np.allclose(matrix_to_quat_xyzw(rot_z(np.pi / 2)), [0, 0, np.sqrt(0.5), np.sqrt(0.5)])


def test_pose_inverse():
    T = make_pose(random_rotation(), rng.normal(size=3))
    assert np.allclose(T @ invert_pose(T), np.eye(4), atol=1e-12)


def test_project_to_so3_gives_rotation():
    M = random_rotation() + 0.01 * rng.normal(size=(3, 3))
    R = project_to_so3(M)
    assert np.allclose(R.T @ R, np.eye(3), atol=1e-12) and np.isclose(np.linalg.det(R), 1)


def test_chordal_mean_known_answers():
    # mean of rotations +a and -a about one axis is the identity
    R1, R2 = rot_z(0.4), rot_z(-0.4)
    assert np.allclose(chordal_mean([R1, R2]), np.eye(3), atol=1e-12)
    # mean of rot(a) and rot(b) about the same axis is rot((a+b)/2)
    assert np.allclose(chordal_mean([rot_x(0.1), rot_x(0.5)]), rot_x(0.3), atol=1e-12)
    # symmetric perturbations about a base rotation average back to the base
    B = random_rotation()
    Rs = [B @ so3_exp(d) for d in ([0.05, 0, 0], [-0.05, 0, 0], [0, 0.03, 0], [0, -0.03, 0])]
    M = chordal_mean(Rs)
    assert rotation_angle_deg(M.T @ B) < 1e-9
    assert np.allclose(M.T @ M, np.eye(3), atol=1e-12) and np.isclose(np.linalg.det(M), 1)
    # the paper's element-wise (R1 + R2) / 2 is NOT a rotation; ours is
    raw = (rot_y(0.6) + rot_y(-0.2)) / 2
    assert abs(np.linalg.det(raw) - 1) > 1e-3
    assert np.allclose(chordal_mean([rot_y(0.6), rot_y(-0.2)]), rot_y(0.2), atol=1e-12)


def test_chordal_mean_rejects_empty():
    with pytest.raises(ValueError):
        chordal_mean([])


def test_project_to_se3_makes_the_rotation_block_rigid_and_keeps_the_translation():
    from stereopath.device.core.geometry import make_pose, project_to_se3, so3_exp

    T = make_pose(so3_exp(np.array([0.1, -0.2, 0.3])), np.array([1.0, 2.0, 3.0]))
    drifted = T.copy()
    drifted[:3, :3] *= 1.001  # a product of many corrections drifts off SO(3)
    drifted[0, 1] += 1e-4
    out = project_to_se3(drifted)
    assert np.allclose(out[:3, :3].T @ out[:3, :3], np.eye(3), atol=1e-12) and np.linalg.det(out[:3, :3]) > 0
    assert np.allclose(out[:3, :3], T[:3, :3], atol=2e-4) and np.array_equal(out[:3, 3], T[:3, 3])
    assert np.array_equal(out[3], [0, 0, 0, 1]) and drifted[0, 0] == T[0, 0] * 1.001  # the input is untouched

"""The one rotations module (fsw.estimation.rotations) against scipy's rotations: one quaternion and stacks
give the same numbers, quaternion ↔ DCM round trips including half turns, tuple forms of the inner loops."""
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from fsw.estimation import rotations as rot

RNG_SEED = 11


def scipy_quat(r: Rotation) -> np.ndarray:
    """scipy's quaternions, scalar first (scipy's own order is scalar last)."""
    return np.roll(r.as_quat(), 1, axis=-1)


def test_stacks_give_the_numbers_of_one_at_a_time():
    """The batched output-error fit and the per-sample filters share these helpers: a stack (..., 4)
    must give exactly what one quaternion at a time gives."""
    rng = np.random.default_rng(RNG_SEED)
    phi = rng.normal(size=(5, 4, 3)) * rng.uniform(1e-13, 3.0, size=(5, 4, 1))
    phi[0, 0] = 0.0
    p, q = rng.normal(size=(5, 4, 4)), rng.normal(size=(5, 4, 4))
    each = np.ndindex(5, 4)
    for i, j in each:
        np.testing.assert_array_equal(rot.quat_exp(phi)[i, j], rot.quat_exp(phi[i, j]))
        np.testing.assert_array_equal(rot.quat_mul(p, q)[i, j], rot.quat_mul(p[i, j], q[i, j]))
        np.testing.assert_array_equal(rot.quat_conj(p)[i, j], rot.quat_conj(p[i, j]))
        np.testing.assert_array_equal(rot.quat_to_dcm(p)[i, j], rot.quat_to_dcm(p[i, j]))
        np.testing.assert_array_equal(rot.skew(phi)[i, j], rot.skew(phi[i, j]))


def test_quaternion_helpers_match_scipy():
    r = Rotation.random(50, random_state=RNG_SEED)
    phi = r.as_rotvec()
    q = rot.quat_exp(phi)
    np.testing.assert_allclose(np.abs(np.sum(q * scipy_quat(r), axis=1)), 1.0, atol=1e-12)   # ±q: one rotation
    np.testing.assert_allclose(rot.quat_to_dcm(q), r.as_matrix(), atol=1e-12)
    np.testing.assert_allclose(rot.quat_to_dcm(rot.quat_mul(q[:-1], q[1:])), (r[:-1] * r[1:]).as_matrix(), atol=1e-12)
    np.testing.assert_allclose(rot.quat_to_dcm(rot.quat_conj(q)), r.inv().as_matrix(), atol=1e-12)
    for k in range(len(phi)):
        np.testing.assert_allclose(rot.quat_log(q[k]), phi[k], atol=1e-12)
        np.testing.assert_allclose(rot.so3_exp(phi[k]), r[k].as_matrix(), atol=1e-12)


@pytest.mark.parametrize("phi", [[0.3, -0.2, 0.5], [np.pi, 0.0, 0.0], [0.0, np.pi - 1e-9, 0.0],
                                 [0.0, 0.0, 1e-10], [2.0, -2.0, 1.0], [0.0, 0.0, 0.0]])
def test_quaternion_and_rotation_vector_from_a_dcm(phi):
    """Shepperd's method from the largest of trace and diagonal: every branch, half turns included; the
    quaternion has w ≥ 0 (one of the two that describe the rotation)."""
    for flip in (np.eye(3), np.diag([1.0, -1.0, -1.0]), np.diag([-1.0, 1.0, -1.0]), np.diag([-1.0, -1.0, 1.0])):
        R = Rotation.from_rotvec(phi).as_matrix() @ flip
        q = rot.quat_from_dcm(R)
        assert q[0] >= 0.0 and abs(np.linalg.norm(q) - 1.0) < 1e-15
        np.testing.assert_allclose(rot.quat_to_dcm(q), R, atol=1e-12)
        v = rot.rotvec_from_dcm(R)
        np.testing.assert_allclose(Rotation.from_rotvec(v).as_matrix(), R, atol=1e-8)


def test_quat_normalize_refuses_what_is_not_a_quaternion():
    np.testing.assert_allclose(rot.quat_normalize([2.0, 0.0, 0.0, 0.0]), [1.0, 0.0, 0.0, 0.0])
    for bad in ([0.0, 0.0, 0.0, 0.0], [np.nan, 1.0, 0.0, 0.0], [1.0, 0.0, 0.0]):
        with pytest.raises(ValueError):
            rot.quat_normalize(bad)


def test_tuple_forms_are_the_array_forms():
    rng = np.random.default_rng(RNG_SEED)
    for _ in range(20):
        p, q = rng.normal(size=4), rng.normal(size=4)
        np.testing.assert_allclose(rot.quat_mul_tuple(tuple(p), tuple(q)), rot.quat_mul(p, q), rtol=0, atol=1e-15)
        phi = rng.normal(size=3) * rng.choice([1e-5, 1.0])
        E, Jr = rot.so3_exp_jr_tuple(*phi)
        np.testing.assert_allclose(np.reshape(E, (3, 3)), rot.so3_exp(phi), atol=1e-14)
        np.testing.assert_allclose(np.reshape(Jr, (3, 3)), rot.so3_right_jacobian(phi), atol=1e-14)


def test_quat_aligning_maps_the_body_field_onto_the_inertial_one():
    rng = np.random.default_rng(RNG_SEED)
    for b_body, b_inertial in [(rng.normal(size=3), rng.normal(size=3)), ([0.0, 0.0, 2.0], [0.0, 0.0, 5.0]),
                               ([0.0, 0.0, 2.0], [0.0, 0.0, -5.0])]:
        for angle in (0.0, 1.0, -2.5):
            q = rot.quat_aligning(b_body, b_inertial, angle)
            u = np.asarray(b_body) / np.linalg.norm(b_body)
            np.testing.assert_allclose(rot.quat_to_dcm(q) @ u, np.asarray(b_inertial) / np.linalg.norm(b_inertial),
                                       atol=1e-12)
    # the angle turns about the body's field direction
    b, a = np.array([1.0, 2.0, 0.5]), np.array([-0.3, 0.2, 1.0])
    R0, R1 = rot.quat_to_dcm(rot.quat_aligning(b, a)), rot.quat_to_dcm(rot.quat_aligning(b, a, 0.7))
    np.testing.assert_allclose(R0.T @ R1, Rotation.from_rotvec(0.7 * b / np.linalg.norm(b)).as_matrix(), atol=1e-12)

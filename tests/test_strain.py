import numpy as np
import scipy.linalg

from skinfem.strain import log_strain


def random_F(rng, n):
    return np.eye(3) + 0.2 * rng.standard_normal((n, 3, 3))


def test_log_strain_matches_matrix_logarithm():
    rng = np.random.default_rng(0)
    F = random_F(rng, 20)
    F = F[np.linalg.det(F) > 0.2]
    E = log_strain(F)
    for Fi, Ei in zip(F, E):
        np.testing.assert_allclose(Ei, 0.5 * scipy.linalg.logm(Fi @ Fi.T).real, atol=1e-12)


def test_log_strain_of_rotation_is_zero_and_stretch_is_log():
    c, s = np.cos(0.7), np.sin(0.7)
    R = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
    np.testing.assert_allclose(log_strain(R[None])[0], 0, atol=1e-14)
    U = np.diag([1.05, 0.95, 1.0])
    np.testing.assert_allclose(np.diag(log_strain((R @ U)[None])[0] @ np.eye(3))[2], 0, atol=1e-14)
    # spatial (left) stretch: ln V = R ln U R^T
    np.testing.assert_allclose(log_strain((R @ U)[None])[0], R @ np.diag(np.log([1.05, 0.95, 1.0])) @ R.T, atol=1e-14)

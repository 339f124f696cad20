"""SE(3) helpers against SciPy and finite differences."""

import numpy as np
import pytest
import warp as wp
from scipy.linalg import expm
from scipy.spatial.transform import Rotation

from warp_devices import devices
from mcgs_warp.geometry import adjoint
from mcgs_warp.kernels.se3 import mat66, se3_adjoint, se3_compose, se3_exp, se3_inverse, se3_log, se3_retract, vec6


@wp.kernel
def se3_eval_kernel(
    xi: wp.array(dtype=vec6),
    eta: wp.array(dtype=vec6),
    exp_out: wp.array(dtype=wp.transform),
    log_out: wp.array(dtype=vec6),
    compose_out: wp.array(dtype=wp.transform),
    inv_out: wp.array(dtype=wp.transform),
    retract_out: wp.array(dtype=wp.transform),
    adj_out: wp.array(dtype=mat66),
):
    i = wp.tid()
    T = se3_exp(xi[i])
    U = se3_exp(eta[i])
    exp_out[i] = T
    log_out[i] = se3_log(T)
    compose_out[i] = se3_compose(T, U)
    inv_out[i] = se3_inverse(T)
    retract_out[i] = se3_retract(T, eta[i])
    adj_out[i] = se3_adjoint(T)


def hat(xi):
    """4x4 matrix of xi = (rho, phi)."""
    rho, phi = xi[:3], xi[3:]
    X = np.zeros((4, 4))
    X[:3, :3] = [[0, -phi[2], phi[1]], [phi[2], 0, -phi[0]], [-phi[1], phi[0], 0]]
    X[:3, 3] = rho
    return X


def to_matrix(t):
    """wp.transform row (px py pz qx qy qz qw) -> 4x4."""
    T = np.eye(4)
    T[:3, :3] = Rotation.from_quat(t[3:]).as_matrix()
    T[:3, 3] = t[:3]
    return T


def run(xi, eta, device):
    n = len(xi)
    outs = [wp.zeros(n, dtype=d, device=device) for d in (wp.transform, vec6, wp.transform, wp.transform, wp.transform, mat66)]
    wp.launch(
        se3_eval_kernel,
        dim=n,
        inputs=[wp.array(xi.astype(np.float32), dtype=vec6, device=device), wp.array(eta.astype(np.float32), dtype=vec6, device=device)],
        outputs=outs,
        device=device,
    )
    return [o.numpy() for o in outs]


@pytest.mark.parametrize("device", devices())
def test_exp_log_compose_inverse_adjoint(device):
    rng = np.random.default_rng(0)
    xi = rng.normal(size=(50, 6)) * np.array([0.5, 0.5, 0.5, 0.8, 0.8, 0.8])
    xi[0] = 0.0
    xi[1, 3:] = [1e-9, 0, 0]  # tiny rotation
    eta = rng.normal(size=(50, 6)) * 0.3
    exp_t, log_x, comp_t, inv_t, retr_t, adj = run(xi, eta, device)
    for k in range(len(xi)):
        T = expm(hat(xi[k]))  # SE(3) exponential via the matrix exponential
        U = expm(hat(eta[k]))
        np.testing.assert_allclose(to_matrix(exp_t[k]), T, atol=2e-6)
        np.testing.assert_allclose(Rotation.from_quat(exp_t[k][3:]).as_rotvec(), Rotation.from_rotvec(xi[k, 3:]).as_rotvec(), atol=2e-6)
        np.testing.assert_allclose(log_x[k], xi[k], atol=5e-6)
        np.testing.assert_allclose(to_matrix(comp_t[k]), T @ U, atol=5e-6)
        np.testing.assert_allclose(to_matrix(inv_t[k]), np.linalg.inv(T), atol=5e-6)
        np.testing.assert_allclose(to_matrix(retr_t[k]), T @ U, atol=5e-6)
        # T Exp(e) T^-1 = Exp(Ad(T) e), and the NumPy twin in mcgs_warp.geometry agrees
        np.testing.assert_allclose(expm(hat(adj[k] @ eta[k])), T @ U @ np.linalg.inv(T), atol=5e-6)
        np.testing.assert_allclose(adjoint(T), adj[k], atol=5e-6)


def test_exp_derivative_at_identity_is_the_generator():
    """d/dt Exp(t xi) at t=0 equals hat(xi) (central differences)."""
    rng = np.random.default_rng(1)
    xi = rng.normal(size=(10, 6))
    h = 1e-3
    plus = run(h * xi, np.zeros_like(xi), "cpu")[0]
    minus = run(-h * xi, np.zeros_like(xi), "cpu")[0]
    for k in range(len(xi)):
        d = (to_matrix(plus[k]) - to_matrix(minus[k])) / (2 * h)
        np.testing.assert_allclose(d, hat(xi[k]), atol=2e-3)

"""The shared Levenberg-Marquardt pieces (mcgs_warp.ba.lm) that MCBA and the keypoint odometry's
window bundle adjustment both step with."""

import numpy as np

from mcgs_warp.ba.lm import LAMBDA_MAX, Damping, damped_step


def test_damped_step_solves_the_free_unknowns_and_holds_the_rest():
    rng = np.random.default_rng(0)
    A = rng.normal(size=(18, 18))
    S = A @ A.T + 18 * np.eye(18)
    x = rng.normal(size=18)
    free = np.arange(6, 18)
    x[:6] = 0.0
    rhs = S @ x
    np.testing.assert_allclose(damped_step(S, rhs, free, 0.0), x, atol=1e-6)  # undamped: the exact answer
    damped = damped_step(S, rhs, free, 10.0)
    assert np.all(damped[:6] == 0.0)
    assert 0 < np.linalg.norm(damped) < 0.5 * np.linalg.norm(x)  # damping shortens the step
    np.testing.assert_array_equal(damped_step(S, rhs, np.zeros(0, int), 1.0), np.zeros(18))


def test_damped_step_is_no_step_where_the_system_cannot_be_trusted():
    S = np.zeros((12, 12))
    S[:6, :6] = 1e12 * np.eye(6)  # the second pose unobserved: only the 1e-9 floor holds it (condition 1e21)
    assert np.all(np.isnan(damped_step(S, np.ones(12), np.arange(12), 1e-4)))
    assert np.all(np.isfinite(damped_step(S, np.ones(12), np.arange(6), 1e-4)))  # held, it is fine
    bad = np.eye(12)
    bad[3, 3] = np.nan  # a linearization gone wrong
    assert np.all(np.isnan(damped_step(bad, np.ones(12), np.arange(12), 1e-4)))


def test_damping_falls_on_success_grows_on_failure_and_ends():
    d = Damping(1e-4)
    d.accepted()
    assert np.isclose(d.lam, 1e-4 / 3)
    for _ in range(100):
        d.accepted()
    assert d.lam == 1e-9  # floor
    d = Damping(1.0)
    d.rejected()
    d.failed()
    assert np.isclose(d.lam, 40.0) and not d.exhausted
    while not d.exhausted:
        d.rejected()
    assert d.lam > LAMBDA_MAX

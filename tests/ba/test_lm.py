"""The shared Levenberg-Marquardt pieces (mcgs_warp.ba.lm) that MCBA, the keypoint odometry's
window bundle adjustment, the two-view motion and the PnP all step with."""

import numpy as np

from mcgs_warp.ba.lm import LAMBDA_MAX, Damping, damped_step, minimize


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


def test_damping_schedules_are_exact():
    """Marquardt's /3 is one division, the PnP's x0.3 one product (not /3.33..., which differs
    in the last bit for 1 in 20 values), x10 and a failed step ending the PnP's solve."""
    d = Damping(1e-4)
    d.accepted()
    assert d.lam == 1e-4 / 3.0
    p = Damping(1e-4, up=10.0, down=(0.3, 1.0), fail=np.inf, lo=0.0, hi=1e4)
    lam = 1e-4
    for _ in range(12):
        p.accepted()
        lam *= 0.3
        assert p.lam == lam  # no floor
    p.rejected()
    assert p.lam == lam * 10.0
    p.failed()
    assert p.exhausted


def test_minimize_keeps_only_steps_that_do_not_raise_the_cost():
    """A 1-D quadratic whose step overshoots where the damping is small: the loop refuses the
    overshoot, damps more and retries on the same linearization, keeps the descending steps,
    and ends where ``accept`` calls it converged; without ``retry`` a refusal uses up an iteration."""
    cost = lambda x: (x - 3.0) ** 2
    for retry in (True, False):
        x, cand, seen = [0.0], [None], []

        def propose(lin, lam):
            cand[0] = x[0] + 2.5 * lin / (1.0 + lam)  # 2.5x too long undamped
            seen.append(lam)
            return cost(cand[0])

        def accept(old, new):
            x[0] = cand[0]
            return old - new < 1e-12

        res = minimize(cost(0.0), lambda lam: 3.0 - x[0], propose, accept, 50, Damping(1.0), retry=retry)
        assert res.accepted > 0 and res.rejected > 0 and res.cost == cost(x[0]) < 1e-10
        assert all(b == a * 4.0 or b == a / 3.0 for a, b in zip(seen, seen[1:]))
    none = minimize(1.0, lambda lam: None, lambda lin, lam: None, None, 5, Damping(1.0))
    assert none.accepted == 0 and none.rejected > 5 and none.cost == 1.0  # no step ever formed: damps until exhausted

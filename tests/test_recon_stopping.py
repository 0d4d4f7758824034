"""The output-error fits' stop in chi-square units (recon.output_error.stopping)."""
import numpy as np
import pytest
from scipy.optimize import least_squares

from recon.estimator.tuning import DEFAULT_TUNING
from recon.output_error.stopping import ChiSquareStop, stop_for_stages

STOP = DEFAULT_TUNING.stop_chi2      # the estimator's default stop (0.01 chi-square unit)

T = np.linspace(0.0, 2.0, 4000)
TRUE = (1.0, 0.7, 9.0)        # amplitude, decay rate [1/s], angular frequency [rad/s]


def ringdown(p):
    a, d, w = p
    return a * np.exp(-d * T) * np.sin(w * T)


def fit(y, sigma, callback=None, model=ringdown):
    def resid(p):
        return (model(p) - y) / sigma
    return least_squares(resid, np.array([0.8, 0.5, 8.6]), method="trf", xtol=1e-14, ftol=1e-14, gtol=1e-14,
                         max_nfev=200, callback=callback)


@pytest.mark.parametrize("sigma", [1e-2, 1e-4])
def test_the_stop_saves_evaluations_and_loses_less_than_its_bound(sigma):
    y = ringdown(TRUE) + sigma * np.random.default_rng(1).standard_normal(T.size)
    full = fit(y, sigma)
    stop = ChiSquareStop(units_per_cost=2.0, rows=T.size, stop_chi2=STOP)      # rows in noise units: chi2 = 2 F
    short = fit(y, sigma, stop)
    assert stop.stopped and short.status == -2
    assert short.nfev < full.nfev
    # what was left on the table is below the stop's own size, in chi-square units
    lost = 2.0 * (short.cost - full.cost)
    assert 0.0 <= lost < STOP
    # and the parameters are the optimum's to far better than their standard errors
    J = full.jac
    se = np.sqrt(np.diag(np.linalg.inv(J.T @ J)))
    assert np.all(np.abs(short.x - full.x) < 0.2 * se)


def test_a_model_that_misses_the_record_is_judged_in_its_residual_s_own_units():
    """Where the model lacks part of the record, the residual's mean square (not the noise) is the
    error variance: the stop comes at a step that is small against that, not against the noise."""
    sigma = 1e-4
    y = ringdown(TRUE) + 0.05 * np.sin(40.0 * T) + sigma * np.random.default_rng(2).standard_normal(T.size)
    noise_only = ChiSquareStop(units_per_cost=2.0, rows=10 ** 12, stop_chi2=STOP)     # as if every row were noise
    both = ChiSquareStop(units_per_cost=2.0, rows=T.size, stop_chi2=STOP)
    a = fit(y, sigma, noise_only)
    b = fit(y, sigma, both)
    assert b.nfev < a.nfev
    # its loss in units of the residual's variance per row stays below the stop's size
    s2 = 2.0 * a.cost / T.size
    assert 2.0 * (b.cost - a.cost) / s2 < STOP


def test_stop_arguments_are_checked():
    with pytest.raises(ValueError, match="units_per_cost"):
        ChiSquareStop(0.0, 10, STOP)
    with pytest.raises(ValueError, match="stop_chi2"):
        ChiSquareStop(1.0, 10, stop_chi2=float("nan"))
    assert stop_for_stages([], STOP) is None
    # a residual of stages scaled per sample count: the largest stage sets the (conservative) unit
    s = stop_for_stages([100, 400], STOP)
    assert s.units_per_cost == pytest.approx(800.0) and s.rows == 500


class _Step:
    """What least_squares hands its callback after an accepted iteration."""
    def __init__(self, x, fun, cost):
        self.x, self.fun, self.cost = np.asarray(x, float), np.asarray(fun, float), float(cost)


def test_a_small_gain_does_not_stop_a_fit_whose_local_model_still_promises_a_unit():
    """A trust region that is still shrinking to where its model holds (a ridge, a sharp switch)
    gains almost nothing per step; the Jacobian at the point says a full step would gain far more.
    The stop waits while that promise is a chi-square unit or more, and stops as before when it
    is not."""
    rng = np.random.default_rng(0)
    J = rng.standard_normal((200, 3))
    x = np.zeros(3)
    promising = J @ np.array([0.3, -0.2, 0.1])            # in J's range: a step removes it
    for f, stops in ((promising, False), (np.zeros(200), True)):
        stop = ChiSquareStop(units_per_cost=2.0, rows=200, stop_chi2=STOP)
        jac = stop.record(lambda p: J)
        jac(x)
        stop(_Step(x, f, 0.5 * f @ f + 1e-6))
        if stops:
            with pytest.raises(StopIteration):
                stop(_Step(x, f, 0.5 * f @ f))
        else:
            assert 2.0 * stop.model_gain(x, f) > 1.0
            stop(_Step(x, f, 0.5 * f @ f))                # a gain of 1e-6: not a stop
            assert not stop.stopped
    # without the Jacobian at the accepted point (another point, or none recorded) it stops on the gain
    stop = ChiSquareStop(units_per_cost=2.0, rows=200, stop_chi2=STOP)
    stop.record(lambda p: J)(x + 1.0)
    stop(_Step(x, promising, 1.0 + 1e-6))
    with pytest.raises(StopIteration):
        stop(_Step(x, promising, 1.0))


def test_a_parameter_pushed_against_its_bound_promises_nothing():
    """The promise counts only steps the fit can take: a parameter at a bound that the full step
    would cross is held there."""
    J = np.array([[1.0, 0.0], [0.0, 1.0], [0.0, 0.0]])
    f = np.array([2.0, 0.0, 0.0])                         # the full step wants p0 -> -2
    x = np.array([0.0, 0.0])
    stop = ChiSquareStop(units_per_cost=2.0, rows=3, stop_chi2=STOP)
    stop.record(lambda p: J, (np.array([0.0, -np.inf]), np.array([np.inf, np.inf])))(x)
    assert stop.model_gain(x, f) == pytest.approx(0.0)
    stop.record(lambda p: J, (np.array([-np.inf, -np.inf]), np.array([np.inf, np.inf])))(x)
    assert stop.model_gain(x, f) == pytest.approx(2.0)   # unbounded: the full step's 0.5 * 2^2
    # the last free parameter held as well: nothing is promised
    J1 = np.array([[1.0], [0.0]])
    stop.record(lambda p: J1, (np.array([0.0]), np.array([np.inf])))(x[:1])
    assert stop.model_gain(x[:1], f[:2]) == pytest.approx(0.0)


def test_output_error_fits_stop_on_their_noise_and_keep_their_answer():
    """The polish of a simulated record: the stop ends the fit where the full tolerance would have
    gone on, and the parameters are the same to far below their uncertainty."""
    from recon.model import HystereticModel
    from recon.output_error import polish as polish_mod
    from recon.output_error.problem import OutputError

    truth = HystereticModel(excitation="base", c_m=4.0, k_m=1500.0, alpha_m=700.0, gamma=150.0, delta=50.0,
                            fn_m={"y^2": 1.5e5})
    t = np.arange(0.0, 4.0, 1e-3)
    u = 3.0 * np.sin(2 * np.pi * 7.0 * t) * np.minimum(t / 0.5, 1.0)
    y = truth.simulate(t, u)[0]
    sigma = 1e-3 * float(np.std(y))
    y = y + sigma * np.random.default_rng(3).standard_normal(y.size)
    start = HystereticModel.from_dict(truth.to_dict())
    start.c_m, start.alpha_m, start.gamma = 5.0, 600.0, 120.0
    item = (t, u, y)
    prob = OutputError(start, [item], noise=[sigma])
    stop = prob.stop(None, STOP)
    assert isinstance(stop, ChiSquareStop)
    fitted, info = polish_mod.polish(start, [item], noise=[sigma], max_nfev=200)
    sol = least_squares(prob.residual, np.zeros(len(prob.keys)), method="trf", x_scale=1.0, max_nfev=200,
                        xtol=1e-14, ftol=1e-15, gtol=1e-15, diff_step=polish_mod.FD_STEP)
    full = prob.build(sol.x)
    assert info["nfev"] < sol.nfev
    for k in ("c_m", "k_m", "alpha_m", "gamma", "delta"):
        assert getattr(fitted, k) == pytest.approx(getattr(full, k), rel=2e-3)

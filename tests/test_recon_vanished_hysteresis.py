"""A term revision whose Bouc-Wen law has vanished (recon.estimator.pipeline).

The equation-error step can put a Bouc-Wen law in for a stiffness term it missed; once the term
selection adds that term, the law falls to nothing with an alpha of either sign, and the model is
inadmissible for that law alone (diagnosis stress #1092). Ground truth: a system with y^2 and no
hysteresis, simulated with known parameters."""
import numpy as np
import pytest

from recon.estimator.fallback import admissible
from recon.estimator.pipeline import _without_vanished_hysteresis
from recon.estimator.tuning import DEFAULT_TUNING
from recon.model import HystereticModel
from recon.steps.bouc_wen import hysteretic_share

NEGLIGIBLE = DEFAULT_TUNING.negligible

TRUTH = HystereticModel("base", c_m=15.4, k_m=111784.0, alpha_m=0.0, gamma=0.0, delta=0.0,
                        fn_m={"y^2": -3.68e6})


@pytest.fixture(scope="module")
def stage():
    fs = 2000.0
    t = np.arange(int(3.0 * fs)) / fs
    u = 50.0 * np.sin(2 * np.pi * 40.0 * t) * np.minimum(1.0, t / 0.5)
    y, _, _ = TRUTH.simulate(t, u)
    y = y + np.random.default_rng(3).normal(0.0, 1e-3 * np.std(y), y.size)
    return t, u, y, (0.0, 0.0, 0.0)


def _with_law(alpha, gamma, delta):
    return HystereticModel("base", c_m=15.0, k_m=TRUTH.k_m * 1.01 - alpha, alpha_m=alpha, gamma=gamma,
                           delta=delta, fn_m={"y^2": -3.5e6})


def test_a_vanished_law_is_dropped_and_the_rest_refitted(stage):
    model = _with_law(-170.0, 8.0, 1.0)
    assert not admissible(model)
    assert hysteretic_share(model, stage[0], stage[1]) < NEGLIGIBLE
    info = {}
    out = _without_vanished_hysteresis(model, stage, info, DEFAULT_TUNING)
    assert info["vanished_hysteresis"]["applied"]
    assert admissible(out)
    assert out.alpha_m == out.gamma == out.delta == 0.0
    assert out.k_m == pytest.approx(TRUTH.k_m, rel=2e-3)
    assert out.c_m == pytest.approx(TRUTH.c_m, rel=0.05)
    assert out.fn_m["y^2"] == pytest.approx(TRUTH.fn_m["y^2"], rel=0.02)


def test_a_law_that_still_carries_force_is_left_alone(stage):
    # inadmissible (alpha < 0) but its z is a fifth of the elastic force: not a vanished law
    model = _with_law(-0.2 * TRUTH.k_m, 50.0, 10.0)
    assert not admissible(model)
    assert hysteretic_share(model, stage[0], stage[1]) > NEGLIGIBLE
    info = {}
    out = _without_vanished_hysteresis(model, stage, info, DEFAULT_TUNING)
    assert out is model
    assert not info["vanished_hysteresis"]["applied"]


def test_a_model_without_hysteresis_has_no_hysteretic_share(stage):
    assert hysteretic_share(TRUTH, stage[0], stage[1]) == 0.0

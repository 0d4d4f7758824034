"""The estimator's tuned numbers as settings (recon.estimator.tuning): validated, carried in
ReconSettings and its JSON, and read by the estimator (no module holds them)."""
import json

import pytest

from recon import ReconSettings
from recon.estimator.tuning import DEFAULT_TUNING, EstimatorTuning, describe
from shakerlab.errors import UserFacingError


def test_a_value_out_of_range_or_unknown_is_refused_naming_it():
    with pytest.raises(ValueError, match=r"simpler_gain = 1.5 is outside \[0, 1\]"):
        EstimatorTuning(simpler_gain=1.5)
    with pytest.raises(ValueError, match="alpha_shares .* is outside"):
        EstimatorTuning(alpha_shares=(0.5, 0.0))
    with pytest.raises(ValueError, match="knees needs at least one value"):
        EstimatorTuning(knees=())
    with pytest.raises(ValueError, match="floor_draws must be a whole number"):
        EstimatorTuning(floor_draws=1.5)
    with pytest.raises(UserFacingError, match="unknown tuning field.*simpler_gian"):
        ReconSettings(tuning={"simpler_gian": 0.3})
    with pytest.raises(UserFacingError, match="ReconSettings.tuning: .*joint_false_alarm"):
        ReconSettings(tuning={"joint_false_alarm": 0.0})


def test_tuning_travels_as_a_table_and_comes_back_the_same():
    """A batch job's [recon] table or a saved result's settings give the tuning as a mapping (lists
    for tuples); the settings made from it equal the original, and its JSON holds every field."""
    s = ReconSettings(tuning=EstimatorTuning(simpler_gain=0.3, knees=(1.0, 2.0, 4.0)))
    d = json.loads(json.dumps(s.to_dict()))
    again = ReconSettings(**d)
    assert again.tuning == s.tuning and again == s
    assert set(d["tuning"]) == {r["name"] for r in describe(DEFAULT_TUNING)}
    assert ReconSettings().tuning is not None and ReconSettings().tuning == DEFAULT_TUNING


def test_every_tuned_number_says_its_meaning_unit_and_range():
    for r in describe(DEFAULT_TUNING):
        lo, hi = r["range"]
        vals = r["value"] if isinstance(r["value"], tuple) else (r["value"],)
        assert r["meaning"] and r["unit"] and all(lo <= v <= hi for v in vals), r


def test_no_estimator_module_keeps_a_tuned_number_of_its_own():
    import importlib
    import pkgutil

    import recon.estimator as est

    names = {r["name"].upper() for r in describe(DEFAULT_TUNING)}
    left = []
    for mod in pkgutil.iter_modules(est.__path__):
        m = importlib.import_module(f"recon.estimator.{mod.name}")
        left += [f"recon.estimator.{mod.name}.{n}" for n in vars(m) if n in names]
    assert not left, left


def test_the_fits_numbers_are_refused_out_of_range_naming_them():
    with pytest.raises(ValueError, match=r"EstimatorTuning.stop_chi2 = 0.0 is outside \(0, 1000\] \(an output-error"):
        EstimatorTuning(stop_chi2=0.0)
    with pytest.raises(ValueError, match="polish_nfev must be a whole number"):
        EstimatorTuning(polish_nfev=60.5)
    with pytest.raises(UserFacingError, match="ReconSettings.tuning: .*band_false_alarm = 1.5 is outside"):
        ReconSettings(tuning={"band_false_alarm": 1.5})


def test_the_low_level_steps_read_the_tuning_they_are_given():
    """The numbers that were module constants of the output-error fits, the admissibility and the
    model input reach them from the tuning: the polish decimates at polish_fs, admissible reads
    split_limit, and the input's band (kept per stage) is made again under another band rule."""
    import numpy as np

    from recon.estimator.fallback import admissible
    from recon.model import HystereticModel
    from recon.output_error.polish import polish
    from recon.signals import input_filter
    from recon.testing.truth import sdof_run

    model = HystereticModel(excitation="base", c_m=4.0, k_m=1500.0, alpha_m=700.0, gamma=150.0, delta=50.0)
    t = np.arange(0.0, 1.0, 1.0 / 8000.0)
    u = 3.0 * np.sin(2 * np.pi * 7.0 * t)
    item = (t, u, model.simulate(t, u)[0])
    assert polish(model, [item], max_nfev=1)[1]["decimation"] == [4]
    assert polish(model, [item], max_nfev=1, tuning=EstimatorTuning(polish_fs=1000.0))[1]["decimation"] == [8]

    split = HystereticModel(excitation="base", c_m=4.0, k_m=-1100.0, alpha_m=1200.0, gamma=150.0, delta=50.0)
    assert not admissible(split) and admissible(split, EstimatorTuning(split_limit=20.0))

    st = sdof_run("base", snr_db=60.0, seed=0)[0].stage("nonlinear")
    default = input_filter(st)
    wider = input_filter(st, tuning=EstimatorTuning(band_grow=1.0))
    assert input_filter(st) is default and wider is not default
    assert wider.band.top > default.band.top

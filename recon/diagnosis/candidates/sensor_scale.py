"""sensor_scale: the tip reading is (1 + e) times the true value."""
from recon.diagnosis.candidates.base import Candidate, start_model
from shakerlab.run_data import BASE


def starts(base, ctx):
    m = start_model(base, {"tip_scale": 0.0}, "sensor_scale")
    return [(m, ["x:tip_scale"], {"x:tip_scale": 0.01}, {"x:tip_scale": (-0.5, 0.5)})]


def conceal(truth, baseline, strength):
    return {"tip_scale": 0.02 * strength}


CANDIDATE = Candidate(
    "sensor_scale",
    "a sensor is mis-calibrated: the tip reading is (1 + e) times the true value "
    "(a base-sensor error of -e looks nearly the same)",
    "model change: y_rec = (1 + e) x_tip - x_base",
    "simulate, then scale the tip channel", ("x:tip_scale",), starts,
    lambda b, c: b.excitation == BASE, signature=("channel",), conceal=conceal,
    # a tip-scale error can be taken up by a spurious Bouc-Wen law in the baseline; the scale fitted
    # from that baseline (as given, refitted, or alone) then ends worse than the baseline, while from
    # the baseline without the law it reaches the true scale
    hysteresis_absorbs=True)

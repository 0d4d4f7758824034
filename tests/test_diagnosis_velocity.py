"""The diagnosis judges a velocity record in velocity (issue 74, "velocity without loss").

A tip recorded by a vibrometer is compared with the models' simulated y' (and the base's
velocity), never with its integrated displacement, whose drift (the vibrometer's 1/f noise, a
random walk after one integration) no model can follow; a constant velocity offset is a nuisance
of every comparison, as in reconstruct's fits. The output effects (channel delay, sensor scale, a
higher mode's reading) act on the measured velocity."""
import numpy as np
import pytest

from recon.diagnosis import rank
from recon.diagnosis.augmented import AugmentedModel
from recon.diagnosis.diagnose import diagnose
from recon.signals import response_target
from recon.testing import independent as ind
from recon.testing.runs import model_of, to_run, true_model
from recon.testing.stress import draw

ROW = 4       # a diagnosis stress row with a concealed channel delay (rig protocol, 2.3 kHz, 63 dB)


def _recording(i: int, quantity: str, fs: float | None = None) -> dict:
    d = draw(i)
    rec = ind.simulate(d["system"], d["protocol"], fs or d["fs"], d["effect"], d["strength"], seed=i,
                       mode_drive=d.get("mode_drive", 0.0))
    return ind.add_noise(rec, d["snr"], i, d["quantisation"], quantity=quantity)


@pytest.fixture(scope="module")
def short():
    """A short draw of the same row at 1 kHz, clean and as velocity."""
    d = draw(ROW)
    rec = ind.simulate(d["system"], d["protocol"], 1000.0, d["effect"], d["strength"], seed=ROW)
    return rec, to_run(ind.add_noise(rec, 60.0, ROW, quantity="velocity"))


def test_prepare_takes_the_velocity(short):
    rec, run = short
    data = rank.prepare(run, model_of(rec["truth"]))
    for d in data:
        st = run.stage(d.name)
        assert d.order == 1 and d.y is response_target(st)[1]
        assert np.array_equal(d.displacement, st.y) and d.x_in.shape == d.y.shape
        # the floor is the velocity record's, not the integrated displacement's
        assert d.noise < 0.01 * d.rms and set(d.noise_parts) == {"v_tip", "v_base"}


def test_truth_simulates_the_velocity_record(short):
    rec, run = short
    am, _ = true_model(rec)
    data = rank.prepare(run, am.baseline)
    for d in data:
        ys = rank.stage_output(am, d, d.initial)
        n = int(1.0 / d.dt)            # the start's transient left out
        assert np.std((ys - d.y)[n:]) < 0.02 * d.rms, d.name


def test_output_effects_act_on_the_velocity():
    """A delay, a scale and a mode's reading in velocity are the derivative of the same effects in
    displacement."""
    fs, n = 2000.0, 4000
    t = np.arange(n) / fs
    xb = 1e-3 * np.sin(2 * np.pi * 7.0 * t) * (1 - np.exp(-t))
    vb = np.gradient(xb, t)
    ab = np.gradient(vb, t)
    base = model_of({"c_m": 3.0, "k_m": 2000.0, "alpha_m": 0.0, "gamma": 0.0, "delta": 0.0, "fn_m": {}})
    am = AugmentedModel(base, {"delay": 1.3e-3, "tip_scale": 0.03, "w2": 900.0, "phi2": 0.2})
    y, _ = am.simulate(t, -ab, xb)
    v, st = am.simulate(t, -ab, vb, order=1)
    assert st.shape == (5, n)
    inner = slice(20, n - 20)
    dy = np.gradient(y, t)
    assert np.max(np.abs(v - dy)[inner]) < 0.01 * np.std(v)


@pytest.mark.slow
@pytest.mark.timeout(900)      # a full diagnosis against a reconstructed baseline
def test_velocity_record_named_as_displacement():
    """The draw recorded as velocity: the concealed effect is named first, as on the same draw
    recorded as displacement (a row of the diagnosis stress bench, named right there). On the code
    that compared the integrated velocity in displacement the velocity record's diagnosis did not
    name it (at the draw's own 2.3 kHz; simulated here at 1 kHz, where it is named as there, in
    half the time)."""
    out = diagnose(to_run(_recording(ROW, "velocity", 1000.0)), baseline="paper").to_dict()
    named = [m["id"] for m in out["missing_physics"]]
    assert named[:1] == [draw(ROW)["effect"]], named

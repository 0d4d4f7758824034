"""The model input cleared of the noise above its band (recon.input_band), on closed-form signals
and on a recording of the independent generator."""
import numpy as np
import pytest

from recon.input_band import BandLimit, band_top
from recon.signals import input_filter
from shakerlab.run_data import Stage

FS = 2000.0
DT = 1.0 / FS


def ramped_tone(n, f=9.0, amp=1e-3, ramp_s=1.0, phase=0.0):
    """A tone whose envelope rises from rest as (1 - cos) over ``ramp_s`` and falls the same way at
    the end: x and its exact second derivative."""
    t = np.arange(n) * DT
    T = t[-1]
    e = np.ones(n)
    r = t < ramp_s
    e[r] = 0.5 * (1 - np.cos(np.pi * t[r] / ramp_s))
    r = t > T - ramp_s
    e[r] = 0.5 * (1 - np.cos(np.pi * (T - t[r]) / ramp_s))
    # e'' for the exact derivative
    de = np.zeros(n)
    dde = np.zeros(n)
    for m, s in ((t < ramp_s, t), (t > T - ramp_s, T - t)):
        de[m] = 0.5 * np.pi / ramp_s * np.sin(np.pi * s[m] / ramp_s) * (1 if s is t else -1)
        dde[m] = 0.5 * (np.pi / ramp_s) ** 2 * np.cos(np.pi * s[m] / ramp_s)
    w = 2 * np.pi * f
    c, sn = np.cos(w * t + phase), np.sin(w * t + phase)
    x = amp * e * sn
    ddx = amp * (dde * sn + 2 * de * w * c - e * w * w * sn)
    return t, x, ddx


def base_stage(t, xb, name="s"):
    return Stage(name, t, {"x_base": xb, "x_tip": 1.5 * xb}, "base")


def test_a_tone_from_rest_gets_its_acceleration_several_times_closer_than_savitzky_golay_alone():
    rng = np.random.default_rng(3)
    t, x, ddx = ramped_tone(40000)
    noisy = x + rng.normal(0, 1e-3 * np.sqrt(np.mean(x ** 2)), x.size)        # 60 dB
    f = input_filter(base_stage(t, noisy))
    assert f.band is not None and f.band.kept_share < 0.05
    u_band = f(f.raw)
    u_sg = f._smoothed(f.raw)
    err_band = np.sqrt(np.mean((u_band + ddx) ** 2))
    err_sg = np.sqrt(np.mean((u_sg + ddx) ** 2))
    assert err_band < err_sg / 4, (err_band, err_sg)
    assert err_band < 2e-3 * np.sqrt(np.mean(ddx ** 2))


def test_a_record_that_starts_and_stops_in_motion_keeps_savitzky_golay_quality_at_its_ends():
    # cut out of a longer tone: the cosine series of an abrupt end rings, the ends come from the
    # local polynomial fit instead (crossfaded into the band)
    rng = np.random.default_rng(4)
    t, x, ddx = ramped_tone(60000)
    sl = slice(17011, 47011)
    tt, xs, dds = t[sl] - t[sl][0], x[sl], ddx[sl]
    noisy = xs + rng.normal(0, 1e-3 * np.sqrt(np.mean(xs ** 2)), xs.size)
    f = input_filter(base_stage(tt, noisy))
    assert f.band is not None and f.band.level_ends == (False, False)
    u_band, u_sg = f(f.raw), f._smoothed(f.raw)
    edge = 3 * f.window
    for part in (slice(0, edge), slice(-edge, None)):
        e_band = np.sqrt(np.mean((u_band + dds)[part] ** 2))
        e_sg = np.sqrt(np.mean((u_sg + dds)[part] ** 2))
        assert e_band < 1.5 * e_sg, (part, e_band, e_sg)
    mid = slice(edge, -edge)
    # the interior still gains (2.1 times closer here: the cut tone leaks above its line, so the
    # band reaches 2.6 times the tone frequency)
    assert np.sqrt(np.mean((u_band + dds)[mid] ** 2)) < np.sqrt(np.mean((u_sg + dds)[mid] ** 2)) / 1.5


def test_noise_alone_and_a_broadband_record_are_left_as_recorded():
    rng = np.random.default_rng(5)
    noise = rng.normal(0, 1.0, 20000)
    top, why = band_top(noise, 101, 3, 1.0)
    assert top is None and "noise" in why
    from scipy.signal import butter, sosfiltfilt
    # content up to 0.8 of the Nyquist frequency, 60 dB above the sensor noise: no floor to clear
    broadband = sosfiltfilt(butter(8, 0.8, output="sos"), rng.normal(0, 1.0, 20000))
    broadband += rng.normal(0, 1e-3, broadband.size)
    top, why = band_top(broadband, 101, 3, 1e-3)
    assert top is None, why
    assert BandLimit.of(noise, 1.0) is None


def test_the_band_is_a_linear_filter_once_fixed():
    # the uncertainty ensemble passes noise draws through the same filter as the recording
    rng = np.random.default_rng(6)
    t, x, _ = ramped_tone(20000)
    b = BandLimit.of(x + rng.normal(0, 1e-6, x.size), 1e-6, 101, 3)
    assert b is not None
    a1, a2 = rng.normal(0, 1e-6, x.size), rng.normal(0, 1e-6, x.size)
    np.testing.assert_allclose(b(a1 + a2, 2, DT), b(a1, 2, DT) + b(a2, 2, DT), atol=1e-9 * np.abs(b(a1, 2, DT)).max())
    with pytest.raises(ValueError, match="does not fit"):
        b(a1[:-1])


def test_independent_recording_seed_0_at_60_db_is_fitted_within_2_percent_from_the_truth():
    # Issue 18's failing draw: stress seed 0 (paper protocol, fs 5177 Hz) at 60 dB. The output-error
    # fit of the nonlinear stage started at the truth ended with delta 6.9 % off while the base
    # sensor's noise went into the simulation through a Savitzky-Golay second derivative; with a
    # noise-free base channel it was 0.8 %. With the input cleared above its band: 1.7 %.
    from recon.testing.runs import model_of, score, to_run
    from recon.testing.stress import stress_system
    from recon.output_error.polish import polish
    from recon.testing import independent as ind

    system, protocol, fs = stress_system(0)
    rec = ind.simulate(system, protocol, fs, seed=0)
    run = to_run(ind.add_noise(rec, 60.0, 0))
    truth = model_of(rec["truth"])
    st = run.stage("nonlinear")
    m, _ = polish(truth, [truth.fit_item(st)], max_nfev=200)
    sc = score(m, rec["truth"])
    assert sc["worst"] < 0.02, sc


def test_independent_recording_seed_6_at_60_db_reconstructs_within_2_percent():
    # Stress seed 6 (paper protocol, fs 2201 Hz) at 60 dB: the polish started from an
    # equation-error estimate with k = 15 against 1200 and stopped at its budget of 60
    # evaluations, alpha 5.9 % off; continued from there (finish.continue_polish) it ends 0.27 % off
    from recon.testing.runs import score, to_run
    from recon.testing.stress import stress_system
    from recon import ReconSettings, reconstruct
    from recon.testing import independent as ind

    system, protocol, fs = stress_system(6)
    rec = ind.simulate(system, protocol, fs, seed=6)
    res = reconstruct(to_run(ind.add_noise(rec, 60.0, 6)), ReconSettings())
    sc = score(res.model, rec["truth"])
    assert sc["exact"] and not sc["inadmissible"], sc
    assert sc["worst"] < 0.02, sc
    assert res.model.provenance["output_error_polish"].get("continued"), res.model.provenance["output_error_polish"]

"""The simulated physics against an independent integration, and each optional effect's signature."""
import numpy as np
import pytest
from scipy.integrate import solve_ivp

from shakerlab.errors import UserFacingError
from sim_backend import physics as ph
from sim_backend.config import load_config
from sim_backend.world import World

QUIET = {"sensors": {"noise_std": 0.0}}


def merge(*dicts):
    out = {}
    for d in dicts:
        for k, v in d.items():
            out.setdefault(k, {}).update(v)
    return out


def run(config=None, f=14.0, vpp=0.5, seconds=4.0, gain=1.0, sweep=None, seed=0):
    """Drive the world directly (no servers) and return (world, x_base, x_tip) readings."""
    w = World(config, speed=None, seed=seed)
    G, A = w.G, w.A
    G[ph.G_OUT], G[ph.G_VPP], G[ph.G_FREQ] = 1.0, vpp, f
    if sweep is not None:
        G[ph.G_SWEEP], G[ph.G_F0], G[ph.G_F1], G[ph.G_TSWEEP] = 1.0, *sweep
    A[ph.A_ENABLE], A[ph.A_GAIN] = 1.0, gain
    n = int(seconds * w.sample_rate)
    w.advance(n)
    steps = np.arange(n)
    return w, w.readings(0, steps), w.readings(1, steps)


def amp_at(x, f, fs):
    t = np.arange(x.size) / fs
    M = np.column_stack([np.cos(2 * np.pi * f * t), np.sin(2 * np.pi * f * t), np.ones_like(t)])
    c, *_ = np.linalg.lstsq(M, x, rcond=None)
    return abs(c[0] - 1j * c[1])


def test_kernel_matches_an_independent_scipy_integration():
    cfg = load_config(QUIET)
    w, xb, xt = run(QUIET, f=13.0, vpp=0.8, seconds=3.0)
    sp, sh, amp = cfg["specimen"], cfg["shaker"], cfg["amplifier"]
    m, M = sp["mass"], sh["armature_mass"]
    a2, a3, b2 = sp["fn_m"]["y^2"], sp["fn_m"]["y^3"], sp["fn_m"]["y^2*dy"]

    def rhs(t, s):
        xb_, vb, y, vy, z = s
        i = amp["transconductance"] * 1.0 * 0.4 * np.sin(2 * np.pi * 13.0 * t)
        r = sp["c_m"] * vy + sp["k_m"] * y + a2 * y**2 + a3 * y**3 + b2 * y**2 * vy + z
        ab = (sh["force_constant"] * i - sh["suspension_stiffness"] * xb_ - sh["suspension_damping"] * vb
              + m * r) / M
        dz = sp["alpha_m"] * vy - sp["gamma"] * abs(vy) * z - sp["delta"] * vy * abs(z)
        return [vb, ab, vy, -r - ab, dz]

    t = np.arange(xb.size) / w.sample_rate
    sol = solve_ivp(rhs, (0, t[-1]), [0.0] * 5, t_eval=t, rtol=1e-9, atol=1e-12, max_step=1e-3)
    ref_b, ref_y = sol.y[0], sol.y[2]
    y = xt - xb
    assert np.max(np.abs(y)) > 1e-3  # millimetres of relative motion
    # the kernel holds the current over each 0.1 ms step: allow 2 % of the amplitude
    assert np.max(np.abs(y - ref_y)) < 0.02 * np.max(np.abs(ref_y))
    assert np.max(np.abs(xb - ref_b)) < 0.02 * np.max(np.abs(ref_b))


def test_nearly_linear_small_and_clearly_nonlinear_large_near_resonance():
    cfg = load_config(QUIET)
    sp = cfg["specimen"]
    fs = cfg["clock"]["sample_rate"]
    k_lin = sp["k_m"] + sp["alpha_m"]
    f_res = np.sqrt(k_lin) / (2 * np.pi)

    def ratio(vpp, f):
        _, xb, xt = run(QUIET, f=f, vpp=vpp, seconds=6.0)
        tail = slice(-int(2 * fs), None)
        return amp_at(xt[tail] - xb[tail], f, fs) / amp_at(xb[tail], f, fs), np.ptp(xt[tail] - xb[tail]) / 2

    def linear(f):
        w = 2 * np.pi * f
        return abs(w**2 / (k_lin - w**2 + 1j * w * sp["c_m"]))

    r_small, y_small = ratio(1.5, 8.0)
    assert 0.1e-3 <= y_small <= 0.3e-3
    assert r_small == pytest.approx(linear(8.0), rel=0.05)
    r_big, y_big = ratio(0.5, f_res)
    assert y_big > 1e-3
    assert r_big < 0.6 * linear(f_res), "hysteresis and nonlinear damping cap the resonance"


@pytest.mark.parametrize("effect,settings", [
    ("coulomb_friction", {"coulomb_friction": 0.5}),
    ("quadratic_damping", {"quadratic_damping": 20.0}),
])
def test_extra_dissipation_lowers_the_resonant_response(effect, settings):
    fs = 10000.0
    _, xb0, xt0 = run(QUIET, f=13.5, vpp=0.4, seconds=4.0)
    _, xb1, xt1 = run(merge(QUIET, {"effects": settings}), f=13.5, vpp=0.4, seconds=4.0)
    y0 = amp_at((xt0 - xb0)[-10000:], 13.5, fs)
    y1 = amp_at((xt1 - xb1)[-10000:], 13.5, fs)
    assert y1 < 0.9 * y0, effect


def test_one_sided_contact_limits_motion_beyond_the_gap():
    _, xb, xt = run(QUIET, f=10.0, vpp=4.0, seconds=4.0)
    y0 = (xt - xb)[-10000:]
    assert y0.max() > 1e-3 and -y0.min() == pytest.approx(y0.max(), rel=0.05)
    cfg = merge(QUIET, {"effects": {"contact_gap": 0.3e-3, "contact_stiffness": 1.0e6}})
    _, xb, xt = run(cfg, f=10.0, vpp=4.0, seconds=4.0)
    y = (xt - xb)[-10000:]
    assert y.max() < 0.45e-3, "stops shortly after the gap"
    assert -y.min() > 1.5 * y.max(), "only one side is stopped"


def test_channel_delay_shifts_the_tip_channel():
    d = 0.0023
    w0, _, xt0 = run(QUIET, seconds=1.0)
    w1, _, xt1 = run(merge(QUIET, {"effects": {"channel_delay": d}}), seconds=1.0)
    k = int(round(d * 10000))
    assert np.array_equal(xt1[k:], xt0[:-k])


def test_scale_errors():
    _, xb0, xt0 = run(QUIET, seconds=1.0)
    _, xb1, xt1 = run(merge(QUIET, {"effects": {"tip_scale_error": 0.03, "base_scale_error": -0.02}}),
                      seconds=1.0)
    assert np.allclose(xt1, 1.03 * xt0, rtol=0, atol=1e-12)
    assert np.allclose(xb1, 0.98 * xb0, rtol=0, atol=1e-12)


def test_stiffness_drift_detunes_over_time():
    fs = 10000.0
    drift = {"effects": {"stiffness_drift": 0.01}}
    _, xb, xt = run(merge(QUIET, drift), f=12.0, vpp=0.2, seconds=20.0)
    y = xt - xb
    early, late = amp_at(y[20000:40000], 12.0, fs), amp_at(y[-20000:], 12.0, fs)
    assert late < 0.8 * early  # stiffer by ~20 %: the resonance moves away from the drive
    _, xb, xt = run(QUIET, f=12.0, vpp=0.2, seconds=20.0)
    y = xt - xb
    assert amp_at(y[-20000:], 12.0, fs) == pytest.approx(amp_at(y[20000:40000], 12.0, fs), rel=0.03)


def test_higher_mode_shows_in_the_tip_spectrum():
    fs = 10000.0
    mode = {"effects": {"higher_mode_frequency": 120.0, "higher_mode_participation": 0.2}}

    def band_power(cfg):
        _, xb, xt = run(cfg, vpp=2.0, seconds=4.0, sweep=(80.0, 160.0, 4.0))
        spec = np.abs(np.fft.rfft(xt - xb)) ** 2
        freqs = np.fft.rfftfreq(xt.size, 1 / fs)
        return spec[(freqs > 110) & (freqs < 130)].sum() / spec[(freqs > 85) & (freqs < 95)].sum()

    assert band_power(merge(QUIET, mode)) > 5 * band_power(QUIET)


def test_noise_level_and_seed():
    _, xb_a, _ = run(None, vpp=0.0001, seconds=0.5, seed=1)
    _, xb_b, _ = run(None, vpp=0.0001, seconds=0.5, seed=1)
    _, xb_c, _ = run(None, vpp=0.0001, seconds=0.5, seed=2)
    assert np.array_equal(xb_a, xb_b)
    assert not np.array_equal(xb_a, xb_c)
    noise = np.diff(xb_a) / np.sqrt(2)  # the motion itself is tiny and smooth
    assert np.std(noise) == pytest.approx(load_config()["sensors"]["noise_std"], rel=0.1)


def test_default_resonance_and_truth():
    w = World(None, speed=None)
    tr = w.truth()
    assert set(tr) == {"c_m", "k_m", "alpha_m", "gamma", "delta", "fn_m"}
    assert set(tr["fn_m"]) == {"y^2", "y^3", "y^2*dy"}
    f_small = np.sqrt(tr["k_m"] + tr["alpha_m"]) / (2 * np.pi)
    assert 8.0 <= f_small <= 20.0
    assert w.specimen_mass == 0.15


@pytest.mark.parametrize("override,needle", [
    ({"specimen": {"k_mm": 1.0}}, "[specimen] unknown field 'k_mm'"),
    ({"specimen": {"mass": -1.0}}, "[specimen] mass: expected a number > 0, got -1.0"),
    ({"sensors": {"noise_std": "loud"}}, "[sensors] noise_std: expected a number >= 0, got 'loud'"),
    ({"specimen": {"fn_m": {"y^2": float("inf")}}}, "[specimen.fn_m] y^2: expected a number"),
    ({"bogus": {}}, "bogus"),
    ({"effects": {"higher_mode_frequency": 5000.0}}, "higher_mode_frequency"),
    ({"effects": {"contact_stiffness": 1e5}}, "contact_gap"),
])
def test_bad_config_names_the_field(override, needle):
    with pytest.raises(UserFacingError) as info:
        load_config(override)
    assert needle in str(info.value)


def test_config_file_errors(tmp_path):
    p = tmp_path / "sim.toml"
    p.write_text("[specimen]\nk_m = 7000.0\n")
    assert load_config(p)["specimen"]["k_m"] == 7000.0
    p.write_text("[specimen\n")
    with pytest.raises(UserFacingError) as info:
        load_config(p)
    assert str(p) in str(info.value)
    with pytest.raises(UserFacingError):
        load_config(tmp_path / "missing.toml")


def test_real_time_clock_follows_the_wall_clock():
    import time
    w = World(None, speed=2.0)
    w.start_clock()

    def reading():
        # the simulated time after catching up, with the wall-clock window it was read in: the clock
        # thread may lag the wall clock on a loaded machine, so each reading is bracketed, not timed
        a = time.monotonic()
        w.catch_up()
        s = w.time
        return s, a, time.monotonic()

    try:
        s0, a0, b0 = reading()
        time.sleep(0.4)
        s1, a1, b1 = reading()
        slack = 2.0 * w.dt + 1e-9
        assert 2.0 * (a1 - b0) - slack <= s1 - s0 <= 2.0 * (b1 - a0) + slack
        assert s1 - s0 >= 2.0 * 0.4 - slack
    finally:
        w.stop_clock()


def test_is_driven_follows_generator_amplifier_and_burst_state():
    w = World(QUIET, speed=None)
    G, A = w.G, w.A
    G[ph.G_VPP], G[ph.G_FREQ] = 0.5, 100.0
    A[ph.A_GAIN] = 1.0
    assert not w.is_driven()
    G[ph.G_OUT] = 1.0
    assert not w.is_driven(), "amplifier disabled"
    A[ph.A_ENABLE] = 1.0
    assert w.is_driven()
    G[ph.G_BURST] = 1.0
    assert not w.is_driven(), "a burst waiting for its trigger outputs nothing"
    G[ph.G_BURST_ACTIVE], G[ph.G_BURST_LEFT] = 1.0, 2 * np.pi * 2  # two cycles
    assert w.is_driven()
    w.advance(250)  # 25 ms > two cycles of 100 Hz
    assert not w.is_driven()
    assert w.state()["current"] == 0.0
    A[ph.A_WD] = 1.0
    G[ph.G_BURST] = 0.0
    assert not w.is_driven(), "muted by the watchdog"


def test_offset_moves_the_response_off_centre_by_f0_over_k():
    # a constant force f0 per unit mass: the relative motion's mean sits off centre by f0 over a
    # stiffness between k (the hysteretic state relaxed) and k + alpha (its initial stiffness)
    cfg = load_config(None)["specimen"]
    f0 = 2.0
    _, xb0, xt0 = run(QUIET, f=8.0, vpp=0.05, seconds=3.0)
    _, xb1, xt1 = run(merge(QUIET, {"effects": {"offset": f0}}), f=8.0, vpp=0.05, seconds=3.0)
    shift = np.mean((xt1 - xb1)[-10000:]) - np.mean((xt0 - xb0)[-10000:])
    assert f0 / (cfg["k_m"] + cfg["alpha_m"]) < -shift < 1.02 * f0 / cfg["k_m"]


@pytest.mark.parametrize("effect,value,term", [("cubic_stiffness", 3.0e8, "y^3"),
                                               ("amplitude_damping", 4.0e5, "y^2*dy")])
def test_effect_terms_add_to_the_specimens_own(effect, value, term):
    base = load_config(None)["specimen"]["fn_m"][term]
    _, xb1, xt1 = run(merge(QUIET, {"effects": {effect: value}}), seconds=1.0)
    _, xb2, xt2 = run(merge(QUIET, {"specimen": {"fn_m": {term: base + value}}}), seconds=1.0)
    assert np.array_equal(xt1, xt2) and np.array_equal(xb1, xb2)
    _, _, xt0 = run(QUIET, seconds=1.0)
    assert not np.array_equal(xt0, xt1)


def test_no_effect_path_is_bit_identical():
    # every new effect at 0 leaves the kernel's input as it was: the same readings, bit for bit
    cfg = {"effects": {"offset": 0.0, "cubic_stiffness": 0.0, "amplitude_damping": 0.0}}
    _, xb0, xt0 = run(None, seconds=0.5, seed=4)
    _, xb1, xt1 = run(cfg, seconds=0.5, seed=4)
    assert np.array_equal(xt0, xt1) and np.array_equal(xb0, xb1)
    P = ph.parameter_vector(load_config(None), 0)
    assert P[ph.P_F0] == 0.0 and P[ph.P_A3] == load_config(None)["specimen"]["fn_m"]["y^3"]

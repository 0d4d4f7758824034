"""recon.backbone: frequency and damping against amplitude from a ring-down, against ground truth
computed independently (a closed-form linear decay; a Duffing decay integrated by scipy)."""
import numpy as np
import pytest
from scipy.integrate import solve_ivp

from recon.backbone import free_decay_backbone
from shakerlab.errors import UserFacingError

FS = 1024.0


def test_linear_decay_gives_its_frequency_and_damping():
    fn, zeta = 18.7, 0.005
    wn = 2 * np.pi * fn
    wd = wn * np.sqrt(1 - zeta ** 2)
    t = np.arange(int(12 * FS)) / FS
    rng = np.random.default_rng(3)
    y = 2e-3 * np.exp(-zeta * wn * t) * np.cos(wd * t + 0.3) + 1e-7 * rng.standard_normal(t.size)
    bb = free_decay_backbone(t, y, fn)
    assert abs(np.median(bb.frequency) - wd / 2 / np.pi) < 1e-3 * fn
    assert abs(np.median(bb.damping) - zeta) < 0.03 * zeta
    # the envelope follows the decay it was made with
    i = bb.t.size // 2
    assert abs(bb.amplitude[i] / (2e-3 * np.exp(-zeta * wn * bb.t[i])) - 1) < 0.01


def test_duffing_decay_follows_the_hardening_backbone():
    """x'' + 2 zeta w0 x' + w0^2 x + k3 x^3 = 0: to first order the frequency at amplitude A is
    w0 sqrt(1 + 3 k3 A^2 / (4 w0^2))."""
    f0, zeta, k3 = 12.0, 0.004, 8e7
    w0 = 2 * np.pi * f0
    t = np.arange(int(20 * FS)) / FS
    sol = solve_ivp(lambda _, s: [s[1], -2 * zeta * w0 * s[1] - w0 ** 2 * s[0] - k3 * s[0] ** 3],
                    (0, t[-1]), [3e-3, 0.0], t_eval=t, rtol=1e-10, atol=1e-13)
    bb = free_decay_backbone(t, sol.y[0], f0, band=0.3)
    freqs = []
    for amp in (2e-3, 1e-3, 5e-4):
        f, z = bb.at(amp)
        expected = f0 * np.sqrt(1 + 0.75 * k3 * amp ** 2 / w0 ** 2)
        assert f is not None and abs(f - expected) < 0.003 * f0, (amp, f, expected)
        assert abs(z - zeta) < 0.1 * zeta
        freqs.append(f)
    assert freqs[0] > freqs[1] > freqs[2]          # hardening: the frequency falls with the amplitude


def test_binned_reports_empty_bins_as_none():
    t = np.arange(int(8 * FS)) / FS
    y = 1e-3 * np.exp(-0.5 * t) * np.sin(2 * np.pi * 20 * t)
    rows = free_decay_backbone(t, y, 20.0).binned([1e-9, 1e-8, 1e-4, 1e-3])
    assert rows[0]["frequency_hz"] is None and rows[0]["samples"] == 0
    assert abs(rows[2]["frequency_hz"] - 20.0) < 0.05


@pytest.mark.parametrize("kw, msg", [
    ({"f_mode": 600.0}, "Nyquist"),
    ({"f_mode": -3.0}, "positive"),
    ({"f_mode": 20.0, "band": 1.5}, "band"),
    ({"f_mode": 0.2}, "too short"),
])
def test_bad_requests_name_the_problem(kw, msg):
    t = np.arange(2048) / FS
    with pytest.raises(UserFacingError, match=msg):
        free_decay_backbone(t, np.sin(2 * np.pi * 20 * t), **kw)


def _duffing_run(path, f0=12.0, zeta=0.004, k3=8e7):
    """A force-excitation run whose stage 'decay' is a Duffing ring-down (scipy, from 3 mm at rest)."""
    from shakerlab.run_data import Run, Stage
    from shakerlab.runfile.reader import save_npz

    w0 = 2 * np.pi * f0
    t = np.arange(int(20 * FS)) / FS
    sol = solve_ivp(lambda _, s: [s[1], -2 * zeta * w0 * s[1] - w0 ** 2 * s[0] - k3 * s[0] ** 3],
                    (0, t[-1]), [3e-3, 0.0], t_eval=t, rtol=1e-10, atol=1e-13)
    run = Run({"decay": Stage("decay", t, {"x": sol.y[0], "force": np.zeros_like(t)}, excitation="force")})
    save_npz(run, path)
    return w0


def test_backbone_command_measured_and_model(tmp_path, capsys):
    """`shakerlab backbone --json`: the measured frequency rises with the amplitude along the Duffing
    backbone; a linear model of the small-amplitude stiffness is flat at f0 in every bin."""
    import json

    from recon.model import HystereticModel
    from shakerlab.cli import main

    run = tmp_path / "decay.npz"
    w0 = _duffing_run(run)
    model = tmp_path / "linear.json"
    HystereticModel("force", c_m=2 * 0.004 * w0, k_m=w0 ** 2, alpha_m=0.0, gamma=0.0, delta=0.0,
                    inv_m=1.0).save(model)
    assert main(["backbone", str(run), "--stage", "decay", "--model", str(model), "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["stage"] == "decay" and abs(out["mode_hz"] - 12.0) < 0.01
    rows = [r for r in out["bins"] if r["frequency_hz"] is not None]
    assert len(rows) >= 6
    for r in rows:
        amp = np.sqrt(r["amplitude_low"] * r["amplitude_high"])
        expected = 12.0 * np.sqrt(1 + 0.75 * 8e7 * amp ** 2 / w0 ** 2)
        assert abs(r["frequency_hz"] - expected) < 0.004 * 12.0, (amp, r)
    modelled = [r for r in rows if r.get("model_frequency_hz") is not None]
    assert modelled and all(abs(r["model_frequency_hz"] - 12.0) < 0.01 for r in modelled)
    assert rows[-1]["frequency_hz"] > rows[0]["frequency_hz"] + 0.1

    assert main(["backbone", str(run), "--stage", "decay"]) == 0
    text = capsys.readouterr().out
    assert "frequency Hz" in text and "damping %" in text

    assert main(["backbone", str(run), "--stage", "decay", "--from", "30"]) == 2
    assert "no samples" in capsys.readouterr().err

"""Rig config and protocol files: the shipped defaults load; bad files name the field."""
import math
import re

import numpy as np
import pytest

from rig import analysis
from rig.config import load_config
from rig.protocol import load_protocol
from shakerlab.cli import main
from shakerlab.errors import UserFacingError


def test_defaults_load_and_agree():
    cfg = load_config()
    proto = load_protocol()
    proto.check_against_limits(cfg.limits)
    assert cfg.limits["max_generator_vpp"] > 0
    assert proto.validation[0]["name"] == "validation"
    assert set(cfg.addresses()) == {"generator", "amplifier", "sensor_base", "sensor_tip"}


def _edit(src: str, old: str, new: str) -> str:
    """Replace the first line setting ``old`` (a key, or ``table.key``-free literal text) with ``new``."""
    key = old.split("=")[0].strip()
    pattern = re.compile(rf"^{re.escape(key)} = [^\n#]*(#[^\n]*)?$", re.M) if "=" in old and "\n" not in old else None
    if pattern is not None and pattern.search(src):
        return pattern.sub(lambda m: new.rstrip("\n"), src, count=1)
    assert old in src, old
    return src.replace(old, new, 1)


RIG_CASES = [
    ("max_generator_vpp = 4.0", "max_generator_vpp = -1.0", r"\[limits\] max_generator_vpp: expected a number > 0, got -1"),
    ("max_generator_vpp = 4.0", "max_generator_vpp = \"high\"", r"\[limits\] max_generator_vpp: expected a number"),
    ("max_generator_vpp = 4.0", "", r"\[limits\] max_generator_vpp: missing"),
    ("block_s = 0.05", "block_s = 0.05\nblok = 1", r"\[acquisition\] unknown field 'blok'"),
    ("device_id = 1", "device_id = 1.5", r"\[amplifier\] device_id: expected an integer"),
    ("gain = 1.0", "gain = 3.0", r"\[amplifier\] gain: 3 exceeds \[limits\] max_amplifier_gain 2"),
    ('address = "127.0.0.1:5020"', 'address = "127.0.0.1"', r"\[amplifier\] address: expected host:port"),
    ("[limits]", "[limits\n", r"not valid TOML"),
]


@pytest.mark.parametrize("old, new, match", RIG_CASES)
def test_bad_rig_config(tmp_path, old, new, match):
    from rig.config import DEFAULT_RIG_PATH

    path = tmp_path / "rig.toml"
    path.write_text(_edit(DEFAULT_RIG_PATH.read_text(), old, new))
    with pytest.raises(UserFacingError, match=match) as err:
        load_config(path)
    assert str(path) in str(err.value)


PROTOCOL_CASES = [
    ("duration_s = 4.0", "duration_s = 0",
     r"\[linear\] duration_s: expected a number > 0, got 0"),
    ('method = "stepped"', 'method = "chirp"', r"\[resonance_search\] method: expected one of 'stepped'"),
    ("steps = 12", "steps = 2", r"\[resonance_search\] steps: expected an integer >= 3"),
    ("stop_hz = 30.0", "stop_hz = 3.0", r"\[resonance_search\] stop_hz \(3\) must exceed start_hz"),
    ("max_vpp = 5.5", "max_vpp = 0.05", r"\[nonlinear\] max_vpp \(0.05\) is below start_vpp"),
    ("step_factor = 1.5", "step_factr = 1.5", r"\[nonlinear\] unknown field 'step_factr'"),
    ("enabled = true", "enabled = false", r"\[nonlinear\] frequency_hz: needed when"),
    ("amplitude_fraction = 1.0", "amplitude_fraction = 1.0\namplitude_vpp = 1.0",
     r"\[validation #1\] give exactly one of amplitude_vpp and amplitude_fraction"),
    ("amplitude_fraction = 1.0", "amplitude_fraction = 1.0\nname = \"check\"",
     r"\[validation #1\] name: 'check' must start with 'validation'"),
    ("thd_threshold = 0.05", "thd_threshold = true", r"\[nonlinear\] thd_threshold: expected a number"),
    ("pre_trigger_s = 0.1", "pre_trigger_s = -0.1", r"\[run\] pre_trigger_s: expected a number >= 0 and <= 10, got -0.1"),
    ("pre_trigger_s = 0.1", "pre_trigger_s = 100", r"\[run\] pre_trigger_s: expected a number >= 0 and <= 10, got 100"),
]


@pytest.mark.parametrize("old, new, match", PROTOCOL_CASES)
def test_bad_protocol(tmp_path, old, new, match):
    from rig.protocol import DEFAULT_PROTOCOL_PATH

    path = tmp_path / "protocol.toml"
    path.write_text(_edit(DEFAULT_PROTOCOL_PATH.read_text(), old, new))
    with pytest.raises(UserFacingError, match=match):
        load_protocol(path)


def test_protocol_amplitude_over_rig_limit(tmp_path):
    from rig.protocol import DEFAULT_PROTOCOL_PATH

    path = tmp_path / "p.toml"
    path.write_text(_edit(DEFAULT_PROTOCOL_PATH.read_text(), "max_vpp = 5.5", "max_vpp = 9.0"))
    with pytest.raises(UserFacingError, match=r"\[nonlinear\] max_vpp = 9: generator amplitude 9 Vpp exceeds limits.max_generator_vpp = 6 Vpp"):
        load_protocol(path).check_against_limits(load_config().limits)


def test_cli_reports_bad_files(tmp_path, capsys):
    bad = tmp_path / "p.toml"
    bad.write_text("[linear]\nfrequency_hz = 'x'\n")
    assert main(["acquire", "--protocol", str(bad), "-o", str(tmp_path / "r.h5")]) == 2
    assert "[linear] frequency_hz: expected a number > 0, got 'x'" in capsys.readouterr().err
    assert main(["acquire", "--config", str(tmp_path / "none.toml"), "-o", str(tmp_path / "r.h5")]) == 2
    assert "rig config file" in capsys.readouterr().err
    assert not (tmp_path / "r.h5").exists()


# ---- analysis ------------------------------------------------------------------------------------

def test_harmonics_and_distortion():
    fs, f = 10000.0, 13.7
    t = np.arange(int(fs * 1.3)) / fs
    w = 2 * math.pi * f
    xb = 1e-4 * np.sin(w * t)
    y = 2e-3 * np.sin(w * t - 0.5) + 1e-4 * np.cos(3 * w * t)
    r = analysis.response(xb, xb + y, fs, f)
    assert r.relative_amplitude == pytest.approx(2e-3, rel=1e-6)
    assert r.gain == pytest.approx(20.0, rel=1e-6)
    assert r.thd == pytest.approx(0.05, rel=1e-6)
    assert r.phase_deg == pytest.approx(-math.degrees(0.5), abs=1e-4)


def test_loss_factor_of_linear_viscous_loop():
    # restoring force per mass of a linear system r = c y' + K y has loss factor c w / |K + i c w|
    fs, f, c, K = 10000.0, 10.0, 8.0, 5000.0
    w = 2 * math.pi * f
    t = np.arange(int(fs)) / fs
    y = 1e-3 * np.sin(w * t)
    r = c * 1e-3 * w * np.cos(w * t) + K * y
    # r = -x_tip''  => x_tip = r / w^2 for a single harmonic
    x_tip = r / w**2
    x_base = x_tip - y
    got = analysis.response(x_base, x_tip, fs, f).loss_factor
    assert got == pytest.approx(c * w / math.hypot(K, c * w), rel=1e-6)


def test_peak_frequency_refines_between_grid_points():
    f = np.geomspace(10, 20, 9)
    fn = 14.2
    v = 1 / np.abs(1 - (f / fn) ** 2 + 0.1j * f / fn)
    assert abs(analysis.peak_frequency(f, v) - fn) < abs(f[np.argmax(v)] - fn)
    assert analysis.peak_frequency([1, 2, 3], [3, 2, 1]) == 1


# ---- docs stay true ----------------------------------------------------------------------------

def test_every_field_is_documented():
    from pathlib import Path

    from rig import config, protocol
    from shakerlab.toml_fields import schema_doc

    root = Path(__file__).resolve().parents[1]
    proto_doc = (root / "docs" / "protocol.md").read_text()
    acq_doc = (root / "docs" / "acquisition.md").read_text()
    for name, _, _ in schema_doc(protocol.SCHEMA):
        assert f"`{name}`" in proto_doc, name
    for name, _, _ in schema_doc(protocol.VALIDATION_SCHEMA):
        assert f"`validation.{name}`" in proto_doc, name
    for name, _, _ in schema_doc(config.SCHEMA):
        assert f"`{name}`" in acq_doc, name


# ---- live ring buffer ----------------------------------------------------------------------------

def test_live_buffer_keeps_the_latest_samples():
    from rig.instruments import Block
    from rig.live import LiveBuffer

    live = LiveBuffer(seconds=0.01, fs=1000.0)  # 10 samples
    for i0 in range(0, 37, 4):
        x = np.arange(i0, i0 + 4, dtype=float)
        live.on_block(Block(index0=i0, fs=1000.0, x_base=x, x_tip=-x, flags_base=np.zeros(4, np.uint8),
                            flags_tip=np.zeros(4, np.uint8), amplitude_vpp=0.5, stage="linear"))
    t, xb, xt = live.latest()
    np.testing.assert_array_equal(xb, np.arange(30, 40))
    np.testing.assert_array_equal(xt, -np.arange(30, 40))
    np.testing.assert_allclose(t, np.arange(30, 40) / 1000.0)
    t, xb, _ = live.latest(0.003)
    np.testing.assert_array_equal(xb, [37, 38, 39])
    assert live.stage == "linear" and live.amplitude_vpp == 0.5

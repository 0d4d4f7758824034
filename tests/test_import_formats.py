"""`shakerlab import` of lab formats (LMS .mat, TDMS, UFF 58), channel maps, quantities and the
time-base check (issue 14; issue 15 item 14). Real files written by each format's own writer."""
from pathlib import Path

import numpy as np
import pytest
import scipy.io

from shakerlab.cli import main
from shakerlab.runfile.reader import load_run, read_info

SHARED = Path(__file__).resolve().parents[2] / "shared" / "data" / "bolted_beam"


def _csv(path, header, cols, fmt=repr):
    lines = [header] + [",".join(fmt(float(v)) for v in row) for row in np.column_stack(cols)]
    path.write_text("\n".join(lines) + "\n")
    return path


def _run(args, capsys):
    code = main(args)
    out = capsys.readouterr()
    return code, out.out + out.err


def test_ten_significant_digits_time_is_accepted_as_uniform(tmp_path, capsys):
    fs = 1024.0
    t = 3.0 + np.arange(16384) / fs                     # 3 .. 19 s: 10 digits leave 1e-8 s steps of rounding
    csv = _csv(tmp_path / "s.csv", "t,force,v", [t, np.sin(5 * t), np.cos(7 * t)], fmt=lambda v: f"{v:.10g}")
    steps = np.diff(np.array([float(f"{v:.10g}") for v in t]))
    assert np.max(np.abs(steps * fs - 1)) > 1e-6        # what recon refused before ("t must be uniformly sampled")
    code, text = _run(["import", "-o", str(tmp_path / "r.h5"), "--linear", str(csv)], capsys)
    assert code == 0, text
    st = load_run(tmp_path / "r.h5").stage("linear")
    assert st.quantities == {"x": "velocity"} and "v" in st.measured
    assert np.max(np.abs(np.diff(st.t) * fs - 1)) < 1e-9
    assert st.fs == pytest.approx(fs, rel=1e-9)
    s = read_info(tmp_path / "r.h5")["stages"]["linear"]["settings"]
    assert "printed precision" in s["time_base"] and s["max_rounding_s"] <= 5e-8


def test_jitter_is_refused_with_line_and_jitter_unless_resample(tmp_path, capsys):
    rng = np.random.default_rng(1)
    t = np.cumsum(rng.uniform(0.5, 1.5, 3000)) / 1000.0     # spacing varying by up to +-50 %
    csv = _csv(tmp_path / "j.csv", "# exported\nt,x_base,x_tip", [t, np.sin(20 * t), np.sin(21 * t)])
    out = tmp_path / "r.h5"
    code, text = _run(["import", "-o", str(out), "--linear", str(csv)], capsys)
    assert code == 2 and not out.exists()
    k = int(np.argmax(np.abs(np.diff(t) - np.median(np.diff(t))))) + 1
    assert f"j.csv: line {k + 3}:" in text and "not uniform (jitter" in text and "--resample" in text
    jit = float(text.split("(jitter ")[1].split(" %")[0])
    assert 30 < jit < 60
    code, text = _run(["import", "-o", str(out), "--linear", str(csv), "--resample"], capsys)
    assert code == 0, text
    st = load_run(out).stage("linear")
    assert np.ptp(np.diff(st.t)) < 1e-12
    # cubic interpolation of a 3 Hz tone sampled at ~1 kHz: far below the signal
    assert np.max(np.abs(st.channels["x_base"] - np.sin(20 * (st.t + t[0])))) < 1e-6


def test_gap_is_refused_even_with_resample(tmp_path, capsys):
    t = np.arange(2000) / 1000.0
    t = np.delete(t, np.arange(700, 720))
    csv = _csv(tmp_path / "g.csv", "t,x_base,x_tip", [t, np.sin(t), np.sin(t)])
    code, text = _run(["import", "-o", str(tmp_path / "r.h5"), "--linear", str(csv), "--resample"], capsys)
    assert code == 2
    assert "g.csv: line 702: a gap of 0.021 s (about 20 sample(s) missing)" in text


def test_tdms_written_by_nptdms_with_map(tmp_path, capsys):
    from nptdms import ChannelObject, TdmsWriter

    fs = 2000.0
    n = 4000
    t = np.arange(n) / fs
    props = {"wf_increment": 1.0 / fs, "wf_start_offset": 0.0}
    path = tmp_path / "rec.tdms"
    with TdmsWriter(path) as w:
        w.write_segment([ChannelObject("Shaker", "Base", np.sin(2 * np.pi * 5 * t), properties=props),
                         ChannelObject("Laser", "Tip", 2 * np.pi * 5 * np.cos(2 * np.pi * 5 * t), properties=props)])
    out = tmp_path / "r.h5"
    code, text = _run(["import", "-o", str(out), "--linear", str(path), "--map", "x_base=Shaker/Base",
                       "--map", "x_tip=Tip:v"], capsys)
    assert code == 0, text
    st = load_run(out).stage("linear")
    assert st.excitation == "base" and st.quantities == {"x_tip": "velocity", "x_base": "displacement"}
    assert st.fs == pytest.approx(fs)
    np.testing.assert_allclose(st.measured["v_tip"], 2 * np.pi * 5 * np.cos(2 * np.pi * 5 * t))
    # integrated tip displacement: the sine; the weighted line removal leaks 0.25 % of the
    # amplitude at the ends over these 10 periods (measured; the share falls with the periods held)
    assert np.max(np.abs(st.channels["x_tip"] - np.sin(2 * np.pi * 5 * t))) < 3e-3
    # no waveform properties: the rate must be declared
    bare = tmp_path / "bare.tdms"
    with TdmsWriter(bare) as w:
        w.write_segment([ChannelObject("g", "f", np.sin(t)), ChannelObject("g", "x", np.cos(t))])
    code, text = _run(["import", "-o", str(tmp_path / "b.h5"), "--linear", str(bare), "--map", "force=f",
                       "--map", "x=x"], capsys)
    assert code == 2 and "carry no time base: give the sampling rate with --fs" in text
    code, text = _run(["import", "-o", str(tmp_path / "b.h5"), "--linear", str(bare), "--map", "force=f",
                       "--map", "x=x", "--fs", "500"], capsys)
    assert code == 0, text
    assert load_run(tmp_path / "b.h5").stage("linear").fs == pytest.approx(500.0)


def test_uff58_written_by_pyuff_quantity_from_the_file(tmp_path, capsys):
    import pyuff

    fs = 1024.0
    n = 2048
    t = np.arange(n) / fs
    path = tmp_path / "rec.uff"
    uff = pyuff.UFF(str(path))
    for i, (name, data, ordinate) in enumerate((("shaker force", np.sin(2 * np.pi * 9 * t), 13),
                                                ("tip velocity", np.cos(2 * np.pi * 9 * t), 11))):
        uff.write_sets(pyuff.prepare_58(
            binary=0, func_type=1, rsp_node=i + 1, rsp_dir=3, ref_node=1, ref_dir=3, id1=name,
            data=data, x=t, abscissa_spacing=1, abscissa_min=0.0, abscissa_inc=1.0 / fs,
            abscissa_spec_data_type=17, ordinate_spec_data_type=ordinate,
            orddenom_spec_data_type=0, z_axis_spec_data_type=0), mode="add" if i else "overwrite")
    out = tmp_path / "r.h5"
    code, text = _run(["import", "-o", str(out), "--nonlinear", str(path), "--map", "force=shaker force",
                       "--map", "x=#1"], capsys)
    assert code == 0, text
    st = load_run(out).stage("nonlinear")
    assert st.excitation == "force" and st.quantities == {"x": "velocity"}
    assert st.fs == pytest.approx(fs, rel=1e-6)
    np.testing.assert_allclose(st.measured["v"], np.cos(2 * np.pi * 9 * t), atol=1e-6)


def _lms_struct(values, fs):
    values = np.asarray(values, float)
    x_values = {"start_value": np.array([[0.0]]), "increment": np.array([[1.0 / fs]]),
                "number_of_values": np.array([[values.shape[0]]]), "quantity": np.array(["Time"])}
    y_values = {"values": values if values.ndim > 1 else values[None, :], "quantity": np.array(["Velocity"])}
    return {"x_values": x_values, "y_values": y_values, "function_record": {"name": np.array(["ch"])}}


def test_lms_mat_synthetic_same_layout(tmp_path, capsys):
    fs = 1024.0
    n = 3000
    t = np.arange(n) / fs
    v = np.cos(2 * np.pi * 18 * t)
    scipy.io.savemat(tmp_path / "Time.mat", {"Time_Laser__X": _lms_struct(v, fs),
                                             "Signal": _lms_struct(np.column_stack([v, 2 * v]), fs)})
    scipy.io.savemat(tmp_path / "TimeShaker.mat", {"Time_Shaker__X": _lms_struct(np.sin(2 * np.pi * 18 * t), fs)})
    out = tmp_path / "r.h5"
    toml = tmp_path / "map.toml"
    toml.write_text('[map]\nforce = "Time_Shaker__X"\nx = "Time_Laser__X:velocity"\n')
    code, text = _run(["import", "-o", str(out), "--linear", str(tmp_path / "Time.mat"),
                       str(tmp_path / "TimeShaker.mat"), "--map-file", str(toml)], capsys)
    assert code == 0, text
    st = load_run(out).stage("linear")
    assert st.quantities == {"x": "velocity"} and st.fs == pytest.approx(fs)
    np.testing.assert_allclose(st.measured["v"], v)
    # a column of a multi-channel struct, and a bad map, are named
    code, text = _run(["import", "-o", str(tmp_path / "r2.h5"), "--linear", str(tmp_path / "Time.mat"),
                       str(tmp_path / "TimeShaker.mat"), "--map", "force=Time_Shaker__X", "--map", "x=Signal[1]:a"],
                      capsys)
    assert code == 0, text
    np.testing.assert_allclose(load_run(tmp_path / "r2.h5").stage("linear").measured["a"], 2 * v)
    code, text = _run(["import", "-o", str(tmp_path / "r3.h5"), "--linear", str(tmp_path / "Time.mat"),
                       "--map", "force=Nope", "--map", "x=Time_Laser__X:v"], capsys)
    assert code == 2 and "--map force=Nope: no channel 'Nope'" in text and "Time_Laser__X" in text


@pytest.mark.parametrize("args, match", [
    (["--map", "tip=A"], "unknown role 'tip'"),
    (["--map", "x_tip"], "expected ROLE=CHANNEL"),
    (["--map", "force=A"], "map x_base and x_tip"),
    (["--map", "v_tip=A:a", "--map", "x_base=B"], "role v_tip says velocity, the suffix says acceleration"),
])
def test_bad_maps_are_named(tmp_path, capsys, args, match):
    csv = _csv(tmp_path / "a.csv", "t,A,B", [np.arange(10.0), np.arange(10.0), np.arange(10.0)])
    code, text = _run(["import", "-o", str(tmp_path / "r.h5"), "--linear", str(csv)] + args, capsys)
    assert code == 2 and match in text


@pytest.mark.skipif(not SHARED.is_dir(), reason="../shared/data/bolted_beam is not beside this clone")
def test_bolted_beam_lms_record_imports(tmp_path, capsys):
    rec = SHARED / "chirp_0p05"
    # a slice: the first 4 s of the record, written back in the same LMS layout
    out_files = []
    for name, key in (("Time.mat", "Time_Laser__X"), ("TimeShaker.mat", "Time_Shaker__X")):
        m = scipy.io.loadmat(rec / name)
        s = m[key][0, 0]
        vals = np.ravel(s["y_values"][0, 0]["values"])[:4096]
        fs = 1.0 / float(s["x_values"][0, 0]["increment"][0, 0])
        scipy.io.savemat(tmp_path / name, {key: _lms_struct(vals, fs)})
        out_files.append(str(tmp_path / name))
    out = tmp_path / "beam.h5"
    code, text = _run(["import", "-o", str(out), "--linear", *out_files, "--map", "x=Time_Laser__X:v",
                       "--map", "force=Time_Shaker__X"], capsys)
    assert code == 0, text
    st = load_run(out).stage("linear")
    assert st.fs == pytest.approx(1024.0) and st.t.size == 4096 and st.quantities == {"x": "velocity"}
    # the whole record straight from the shared files
    code, text = _run(["import", "-o", str(tmp_path / "full.h5"), "--linear", str(rec / "Time.mat"),
                       str(rec / "TimeShaker.mat"), "--map", "x=Time_Laser__X:v", "--map", "force=Time_Shaker__X"],
                      capsys)
    assert code == 0, text
    assert "16384 samples at 1024 Hz" in text

"""The HDF5 run file: round trip, crash safety, results written back only into clean files."""
import os
import signal
import subprocess
import sys
import time

import h5py
import numpy as np
import pytest

from shakerlab.errors import UserFacingError
from shakerlab.runfile.writer import RunWriter
from shakerlab.runfile.results import add_result, open_for_results, read_results, recover_copy
from shakerlab.runfile.reader import load_run, read_events, read_info, read_run


def _write(path, n=5000, fs=1000.0):
    t = np.arange(n) / fs
    xb = 1e-3 * np.sin(2 * np.pi * 5 * t)
    xt = 2e-3 * np.sin(2 * np.pi * 5 * t + 0.3)
    with RunWriter(path) as w:
        w.set_text("protocol_toml", "[linear]\nfrequency_hz = 5.0\n")
        w.set_instrument("generator", identity="ACME,GEN,1", address="socket://127.0.0.1:1", settings={"fs": fs})
        w.log("info", "hello", run_time=0.0)
        st = w.begin_stage("linear", fs=fs, start_index=100, settings={"frequency_hz": 5.0, "amplitude_vpp": 0.2})
        for i in range(0, n, 1024):
            j = min(n, i + 1024)
            st.append(100 + i, {"x_base": xb[i:j], "x_tip": xt[i:j]})
        st.add_step(100, 0.2, 5.0, "dwell")
        st.close(summary={"gain": 2.0})
        st2 = w.begin_stage("resonance_search", fs=fs, start_index=100 + n)
        st2.append(100 + n, {"x_base": xb[:10], "x_tip": xt[:10]})
    return t, xb, xt


def test_round_trip(tmp_path):
    path = tmp_path / "run.h5"
    t, xb, xt = _write(path)
    run = load_run(path)
    assert list(run.stages) == ["linear", "resonance_search"]
    lin = run.stage("linear")
    np.testing.assert_array_equal(lin.channels["x_tip"], xt)
    np.testing.assert_allclose(lin.t, t)
    assert lin.settings["frequency_hz"] == 5.0
    assert lin.settings["summary"] == {"gain": 2.0}
    assert lin.settings["steps"][0]["label"] == "dwell"
    assert lin.settings["t0"] == pytest.approx(0.1)
    assert run.attrs["clean_close"] is True
    info = read_info(path)
    assert info["status"] == "complete"
    assert info["instruments"]["generator"]["identity"] == "ACME,GEN,1"
    assert "frequency_hz" in info["config"]["protocol_toml"]
    assert [e["message"] for e in read_events(path)] == ["hello"]
    with h5py.File(path, "r") as f:
        assert f["entry/stages/linear/x_tip"].chunks is not None
        assert f["entry/stages/linear/x_tip"].maxshape == (None,)
        assert f["entry"].attrs["NX_class"] == "NXentry"
        assert not f.swmr_mode


def test_refuses_overwrite_and_foreign_files(tmp_path):
    path = tmp_path / "run.h5"
    _write(path)
    with pytest.raises(UserFacingError, match="file exists"):
        RunWriter(path)
    with h5py.File(tmp_path / "other.h5", "w") as f:
        f["x"] = 1
    with pytest.raises(UserFacingError, match="not a shakerlab run file"):
        read_run(tmp_path / "other.h5")
    (tmp_path / "junk.h5").write_bytes(b"not hdf5")
    with pytest.raises(UserFacingError, match="not a readable HDF5 file"):
        read_run(tmp_path / "junk.h5")


def test_flagged_samples_are_refused(tmp_path):
    path = tmp_path / "run.h5"
    with RunWriter(path) as w:
        st = w.begin_stage("linear", fs=100.0)
        flags = np.zeros(50, np.uint8)
        flags[7] = 1
        st.append(0, {"x_base": np.zeros(50), "x_tip": np.where(flags, np.nan, 0.0)}, flags={"x_tip": flags})
    with pytest.raises(UserFacingError, match="'linear' channel 'x_tip' has 1 flagged sample.*first at sample 7"):
        read_run(path)


def test_results_only_into_clean_files(tmp_path):
    path = tmp_path / "run.h5"
    _write(path)
    name = add_result(path, "reconstruction", {"parameters": {"k_m": 1.5}}, text="y'' + ...")
    assert name == "/entry/results/reconstruction_000"
    assert add_result(path, "reconstruction", {"a": 1}).endswith("reconstruction_001")
    assert read_results(path)["reconstruction_000"]["parameters"]["k_m"] == 1.5
    # the recorded data is untouched
    assert load_run(path).stage("linear").t.size == 5000


WRITER = r"""
import sys, time, numpy as np
from shakerlab.runfile.writer import RunWriter
w = RunWriter(sys.argv[1], flush_interval=0.2)
st = w.begin_stage("linear", fs=1000.0)
i = 0
while True:
    st.append(i, {"x_base": np.full(100, 1.0), "x_tip": np.arange(i, i + 100, dtype=float)})
    i += 100
    if i == 3000:
        print("ready", flush=True)
    time.sleep(0.01)
"""


def test_sigkill_leaves_a_readable_file(tmp_path):
    path = tmp_path / "crash.h5"
    partial = tmp_path / "crash.h5.partial"   # recorded under this name until closed
    proc = subprocess.Popen([sys.executable, "-c", WRITER, str(path)], stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdout.readline().strip() == "ready"
        time.sleep(0.5)
    finally:
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait()
    assert not path.exists()
    with pytest.raises(UserFacingError, match=r"crash\.h5\.partial holds its recording.*--recover"):
        read_run(path)  # the message says where the data is
    run = read_run(partial)  # opens directly, no h5clear
    x_tip = run.stage("linear").channels["x_tip"]
    assert x_tip.size >= 3000
    np.testing.assert_array_equal(x_tip, np.arange(x_tip.size))  # consistent up to the last flush
    assert run.attrs["clean_close"] is False
    assert run.attrs["status"] == "running"
    with pytest.raises(UserFacingError, match="not closed cleanly.*--recover"):
        open_for_results(partial)
    with pytest.raises(UserFacingError, match="not closed cleanly"):
        add_result(partial, "reconstruction", {})
    # a new recording under the same name refuses while the partial file is there
    with pytest.raises(UserFacingError, match="interrupted recording.*--recover"):
        RunWriter(path)
    copy = recover_copy(partial, path)         # recovered under the run's own name
    assert read_info(copy)["status"] == "recovered"
    assert read_info(copy)["stages"]["linear"]["status"] == "interrupted"
    assert add_result(copy, "reconstruction", {"ok": True})
    np.testing.assert_array_equal(load_run(copy).stage("linear").channels["x_tip"], x_tip)
    assert "recovered copy" in read_events(copy)[-1]["message"]
    # the crashed original was never modified
    assert read_run(partial).attrs["clean_close"] is False

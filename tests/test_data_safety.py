"""Issue 15, items 5-13 and 15-17: no file lost or changed by a bad command, clear errors (exit 2, the
file and field named) instead of tracebacks, and plausibility warnings. Real run files, real CLI runs
(in this process through ``shakerlab.cli.main``, or as a separate process where a second process is the
point), and every test checks that the files it started with are still there, byte for byte."""
import hashlib
import json
import re
import signal
import subprocess
import sys
import time

import h5py
import numpy as np
import pytest

from recon.model import HystereticModel
from shakerlab.cli import main
from shakerlab.errors import UserFacingError
from shakerlab.output_files import OutputLock
from shakerlab.runfile.reader import load_run, read_info, read_run
from shakerlab.runfile.results import read_results
from shakerlab.runfile.writer import RunWriter
from sim_backend.rig import SimulatedRig
from workflows.batch import write_simulated_run
from workflows.plausibility import run_warnings

from test_rig_acquisition import SMALL_PROTOCOL
from test_rig_cli import _config_for


def digest(path) -> str:
    return hashlib.sha256(open(path, "rb").read()).hexdigest()


@pytest.fixture(scope="module")
def run_file(tmp_path_factory):
    d = tmp_path_factory.mktemp("safety")
    write_simulated_run(d / "run.h5", fs=1000.0, duration=4.0, seed=3)
    return d / "run.h5"


@pytest.fixture
def run_copy(run_file, tmp_path):
    path = tmp_path / "run.h5"
    path.write_bytes(run_file.read_bytes())
    return path


def exit_and_error(argv, capsys):
    code = main([str(a) for a in argv])
    return code, capsys.readouterr().err


def _csv(path, n=200):
    t = np.arange(n) / 500.0
    rows = "\n".join(f"{float(a)!r},{float(b)!r},{float(c)!r}" for a, b, c in zip(t, np.sin(t), 2 * np.sin(t)))
    path.write_text("t,x_base,x_tip\n" + rows + "\n")
    return path


# ---- item 5: temporary file + rename, advisory lock, the file checked at the end -----------------------

def test_item5_import_force_refuses_a_file_that_acquire_is_writing(tmp_path, run_file, capsys):
    out = tmp_path / "X.h5"
    out.write_bytes(run_file.read_bytes())          # an earlier run, replaced (--force) only at the end
    before = digest(out)
    proto = tmp_path / "p.toml"
    proto.write_text(SMALL_PROTOCOL)
    proc = subprocess.Popen([sys.executable, "-m", "shakerlab.cli", "acquire", "--sim-speed", "1", "--protocol",
                             str(proto), "-o", str(out), "--force"],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        lines = []
        deadline = time.monotonic() + 90
        while time.monotonic() < deadline:
            line = proc.stdout.readline()
            lines.append(line)
            if "stage linear begins" in line or not line:
                break
        assert "stage linear begins" in lines[-1], "".join(lines)
        assert (tmp_path / "X.h5.partial").exists() and (tmp_path / "X.h5.lock").exists()
        code, err = exit_and_error(["import", "--force", "-o", out, "--linear", _csv(tmp_path / "a.csv")], capsys)
        assert code == 2
        assert "another shakerlab process" in err and "X.h5.lock" in err and "nothing was changed" in err
        assert digest(out) == before                 # the old file: intact while the new one is recorded
        code, err = exit_and_error(["import", "--recover", run_file, "-o", out, "--force"], capsys)
        assert code == 2 and "another shakerlab process" in err
        assert digest(out) == before
        proc.send_signal(signal.SIGINT)
        rest, _ = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 130, rest
    assert re.search(r"checked: \d+ samples per channel read back from .*X\.h5", rest), rest
    info = read_info(out)                            # now the new (aborted) run, renamed into place
    assert info["status"] == "aborted" and info["clean_close"]
    assert not (tmp_path / "X.h5.partial").exists() and not (tmp_path / "X.h5.lock").exists()


def test_item5_a_failed_write_leaves_the_existing_file(run_copy):
    before = digest(run_copy)
    with pytest.raises(RuntimeError, match="disk full"):
        with RunWriter(run_copy, overwrite=True) as w:
            w.begin_stage("linear", fs=100.0).append(0, {"x_base": np.zeros(5), "x_tip": np.zeros(5)})
            raise RuntimeError("disk full")
    assert digest(run_copy) == before
    assert sorted(p.name for p in run_copy.parent.iterdir()) == ["run.h5"]   # no partial, no lock left


def test_item5_writer_reads_its_file_back_before_renaming(tmp_path):
    path = tmp_path / "new.h5"
    with RunWriter(path) as w:
        w.begin_stage("linear", fs=100.0).append(0, {"x_base": np.zeros(50), "x_tip": np.ones(50)})
        assert (tmp_path / "new.h5.partial").exists() and not path.exists()
    assert w.renamed and w.problems == [] and path.exists()
    # a stage whose datasets do not hold what was appended fails the check and stays partial
    path2 = tmp_path / "bad.h5"
    w = RunWriter(path2)
    sw = w.begin_stage("linear", fs=100.0)
    sw.append(0, {"x_base": np.zeros(50), "x_tip": np.ones(50)})
    sw.group["x_tip"].resize((40,))                  # what a lost write would leave
    w.close()
    assert not w.renamed and "stage 'linear' dataset 'x_tip': 40 samples stored, 50 written" in w.problems[0]
    assert not path2.exists() and (tmp_path / "bad.h5.partial").exists()


def test_item5_lock_held_by_another_process_refuses_any_writer(run_copy, tmp_path, capsys):
    holder = subprocess.Popen([sys.executable, "-c", "import sys, time\nfrom shakerlab.output_files import OutputLock\n"
                               "l = OutputLock(sys.argv[1]).acquire()\nprint('locked', flush=True)\ntime.sleep(60)",
                               str(run_copy)], stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "locked"
        before = digest(run_copy)
        with pytest.raises(UserFacingError, match=rf"pid {holder.pid}.*is writing this file"):
            RunWriter(run_copy, overwrite=True)
        with pytest.raises(UserFacingError, match="another shakerlab process"):
            OutputLock(run_copy).acquire()
        assert digest(run_copy) == before
    finally:
        holder.kill()
        holder.wait()
    with OutputLock(run_copy):                       # released by the kernel when the holder died
        pass


def test_item5_acquire_refuses_while_an_interrupted_recording_is_there(tmp_path, capsys):
    partial = tmp_path / "r.h5.partial"
    partial.write_bytes(b"the data of a crashed recording")
    proto = tmp_path / "p.toml"
    proto.write_text(SMALL_PROTOCOL)
    code, err = exit_and_error(["acquire", "--sim-speed", "0", "--protocol", proto, "-o", tmp_path / "r.h5"], capsys)
    assert code == 2
    assert "r.h5.partial" in err and "interrupted recording" in err and "--recover" in err
    assert partial.read_bytes() == b"the data of a crashed recording"


# ---- item 6: --recover onto its own input ----------------------------------------------------------

def test_item6_recover_refuses_its_input_as_output(run_copy, capsys):
    before = digest(run_copy)
    for other in (run_copy, run_copy.parent / "." / run_copy.name):
        code, err = exit_and_error(["import", "--recover", run_copy, "-o", other, "--force"], capsys)
        assert code == 2 and "the output is the input file" in err
        assert digest(run_copy) == before


def test_item6_recover_force_replaces_another_file_only_when_complete(run_copy, tmp_path, capsys):
    dst = tmp_path / "copy.h5"
    dst.write_bytes(b"old")
    code, err = exit_and_error(["import", "--recover", run_copy, "-o", dst], capsys)
    assert code == 2 and "file exists" in err and dst.read_bytes() == b"old"
    broken = tmp_path / "broken.h5"
    broken.write_bytes(run_copy.read_bytes()[: run_copy.stat().st_size // 2])
    code, err = exit_and_error(["import", "--recover", broken, "-o", dst, "--force"], capsys)
    assert code == 2 and "broken.h5" in err and dst.read_bytes() == b"old"
    assert main(["import", "--recover", str(run_copy), "-o", str(dst), "--force"]) == 0
    assert read_info(dst)["status"] == "recovered"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["broken.h5", "copy.h5", "run.h5"]


# ---- item 7: --save-model never over an existing file without --force, never over a run file ----------

@pytest.mark.parametrize("command", ["reconstruct", "diagnose"])
def test_item7_save_model_never_replaces_a_run_file(run_copy, command, capsys):
    before = digest(run_copy)
    for force in ([], ["--force"]):
        t0 = time.monotonic()
        code, err = exit_and_error([command, run_copy, "--save-model", run_copy, *force], capsys)
        assert code == 2 and "HDF5 file" in err and "never overwritten" in err
        assert time.monotonic() - t0 < 5            # refused before the reconstruction
        assert digest(run_copy) == before


def test_item7_save_model_needs_force_for_an_existing_json(run_copy, tmp_path, capsys):
    model = tmp_path / "m.json"
    model.write_text("{\"keep\": true}")
    code, err = exit_and_error(["reconstruct", run_copy, "--save-model", model, "--no-polish"], capsys)
    assert code == 2 and "file exists" in err and "--force" in err
    assert model.read_text() == "{\"keep\": true}"
    assert main(["reconstruct", str(run_copy), "--save-model", str(model), "--no-polish", "--force"]) == 0
    assert HystereticModel.load(model).excitation == "base"
    assert not list(tmp_path.glob(".*tmp*"))         # no temporary file left


# ---- item 8: acquire --force with a setting the instrument refuses ----------------------------------

def test_item8_acquire_force_checks_the_devices_before_touching_the_old_file(tmp_path, run_file, capsys):
    old = tmp_path / "old.h5"
    old.write_bytes(run_file.read_bytes())
    before = digest(old)
    proto = tmp_path / "p.toml"
    proto.write_text(SMALL_PROTOCOL)
    with SimulatedRig({"amplifier": {"max_gain": 1.0}}, speed=1.0, seed=2) as sim:
        cfg = _config_for(sim, tmp_path)
        text = cfg.read_text()
        cfg.write_text(re.sub(r"^gain = 1\.0", "gain = 1.5", text, count=1, flags=re.M))  # <= max_amplifier_gain 2
        code, err = exit_and_error(["acquire", "--config", cfg, "--protocol", proto, "-o", old, "--force"], capsys)
        assert not sim.world.is_driven()
    assert code == 2
    assert "gain: 1.5 exceeds the amplifier's own maximum 1" in err and "nothing was driven" in err
    assert digest(old) == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["old.h5", "p.toml", "rig.toml"]


# ---- item 9 and 13: report into an existing directory; the report first, then the write-back ----------

def test_item9_report_into_an_existing_report_needs_force(run_copy, tmp_path, capsys):
    rep = tmp_path / "rep"
    rep.mkdir()
    (rep / "index.html").write_text("an earlier report")
    code, err = exit_and_error(["report", run_copy, "-o", rep], capsys)
    assert code == 2 and "not empty" in err and "--force" in err
    assert (rep / "index.html").read_text() == "an earlier report"
    (tmp_path / "afile").write_text("x")
    code, err = exit_and_error(["report", run_copy, "-o", tmp_path / "afile"], capsys)
    assert code == 2 and "not a directory" in err and (tmp_path / "afile").read_text() == "x"


@pytest.mark.slow
def test_item13_report_is_written_first_and_says_when_the_write_back_cannot_be_done(run_copy, tmp_path, capsys):
    rep = tmp_path / "rep"
    rep.mkdir()
    (rep / "index.html").write_text("an earlier report")
    (rep / "notes.txt").write_text("mine")
    before = digest(run_copy)
    holder = subprocess.Popen([sys.executable, "-c", "import sys, time\nfrom shakerlab.output_files import OutputLock\n"
                               "l = OutputLock(sys.argv[1]).acquire()\nprint('locked', flush=True)\ntime.sleep(120)",
                               str(run_copy)], stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "locked"
        code = main(["report", str(run_copy), "-o", str(rep), "--force", "--no-uncertainty", "--no-polish"])
        out = capsys.readouterr().out
    finally:
        holder.kill()
        holder.wait()
    assert code == 0
    assert "not written back" in out and "another shakerlab process" in out
    html = (rep / "index.html").read_text()
    assert "Reconstruction report" in html and "not written back" in html
    assert json.loads((rep / "result.json").read_text())["report"]["result_group"] is None
    assert (rep / "notes.txt").read_text() == "mine"          # --force replaces report files only
    assert digest(run_copy) == before and read_results(run_copy) == {}
    assert not list(tmp_path.glob(".rep.*"))                  # the staging directory is gone
    # the lock released: the same report now writes the result back (into a copy renamed over the file)
    assert main(["report", str(run_copy), "-o", str(rep), "--force", "--no-uncertainty", "--no-polish"]) == 0
    assert "written into the run file as entry/results/reconstruction_000" in capsys.readouterr().out
    assert list(read_results(run_copy)) == ["reconstruction_000"]
    np.testing.assert_array_equal(read_run(run_copy).stage("linear").y, load_run(run_copy).stage("linear").y)


# ---- item 10: damaged run files -------------------------------------------------------------------

def _edited(run_copy, edit):
    with h5py.File(run_copy, "a") as f:
        edit(f)
    return run_copy


@pytest.mark.parametrize("edit, match", [
    (lambda f: f.__delitem__("entry/stages/nonlinear/x_tip"), r"dataset /entry/stages/nonlinear/x_tip is missing"),
    (lambda f: f["entry/stages/linear"].attrs.__setitem__("settings_json", "{not json"),
     r"attribute 'settings_json' of /entry/stages/linear is not valid JSON"),
    (lambda f: f["entry/stages/linear"].attrs.__setitem__("summary_json", "[1, 2]"),
     r"attribute 'summary_json' of /entry/stages/linear is not a JSON object"),
])
def test_item10_damaged_run_file_is_named_under_reconstruct_and_recover(run_copy, tmp_path, edit, match, capsys):
    _edited(run_copy, edit)
    before = digest(run_copy)
    code, err = exit_and_error(["reconstruct", run_copy], capsys)
    assert code == 2 and re.search(match, err) and str(run_copy) in err
    code, err = exit_and_error(["diagnose", run_copy], capsys)
    assert code == 2 and re.search(match, err)
    assert digest(run_copy) == before


@pytest.mark.parametrize("damage", ["truncated", "superblock", "middle"])
def test_item10_corrupted_file_is_a_clear_error(run_copy, tmp_path, damage, capsys):
    data = bytearray(run_copy.read_bytes())
    rng = np.random.default_rng(0)
    if damage == "truncated":
        data = data[: len(data) * 2 // 3]
    elif damage == "superblock":
        data[8:64] = rng.integers(0, 256, 56, dtype=np.uint8).tobytes()
    else:                                   # the object headers and B-trees near the start of the data
        data[800:4000] = rng.integers(0, 256, 3200, dtype=np.uint8).tobytes()
    run_copy.write_bytes(bytes(data))
    before = digest(run_copy)
    code, err = exit_and_error(["import", "--recover", run_copy, "-o", tmp_path / "copy.h5"], capsys)
    assert code in (0, 2), err
    if code == 2:
        assert "run.h5" in err and "Traceback" not in err
        assert not (tmp_path / "copy.h5").exists()
    code, err = exit_and_error(["reconstruct", run_copy, "--no-polish"], capsys)
    assert code == 2 and "run.h5" in err
    assert digest(run_copy) == before


# ---- item 11: bad numbers in a model JSON ---------------------------------------------------------

@pytest.mark.parametrize("value, match", [
    ('"abc"', r"'parameters.c_m' is 'abc', expected a number"),
    ("NaN", r"'parameters.c_m' is nan, expected a finite number"),
    ("1e999", r"'parameters.c_m' is inf, expected a finite number"),
    ("true", r"'parameters.c_m' is True, expected a number"),
])
def test_item11_model_json_with_a_bad_number_names_the_field(run_copy, tmp_path, value, match, capsys):
    good = HystereticModel("base", c_m=1.0, k_m=100.0, alpha_m=50.0, gamma=10.0, delta=5.0, fn_m={"y^3": 1e6})
    text = good.to_json().replace('"c_m": 1.0', f'"c_m": {value}', 1)
    assert text != good.to_json()
    model = tmp_path / "m.json"
    model.write_text(text)
    code, err = exit_and_error(["diagnose", run_copy, "--baseline", model], capsys)
    assert code == 2 and re.search(match, err) and "m.json" in err
    assert model.read_text() == text
    fn_bad = good.to_dict()
    fn_bad["parameters"]["fn_m"] = {"y^3": "x"}
    with pytest.raises(UserFacingError, match=r"parameters.fn_m\['y\^3'\]"):
        HystereticModel.from_dict(fn_bad)


# ---- item 12: --sim-speed nan, output paths checked before computing -------------------------------

def test_item12_sim_speed_nan(tmp_path, capsys):
    for bad in ("nan", "inf", "-1"):
        code, err = exit_and_error(["acquire", "--sim-speed", bad, "-o", tmp_path / "r.h5"], capsys)
        assert code == 2 and "--sim-speed must be a finite number >= 0" in err
    assert list(tmp_path.iterdir()) == []


def test_item12_output_paths_are_checked_before_computing(run_copy, tmp_path, capsys):
    t0 = time.monotonic()
    code, err = exit_and_error(["reconstruct", run_copy, "--save-model", tmp_path / "nodir" / "m.json"], capsys)
    assert code == 2 and "nodir does not exist" in err
    (tmp_path / "plots").write_text("a file")
    code, err = exit_and_error(["reconstruct", run_copy, "--plots", tmp_path / "plots"], capsys)
    assert code == 2 and "--plots" in err and "not a directory" in err
    code, err = exit_and_error(["diagnose", run_copy, "--report", tmp_path / "plots"], capsys)
    assert code == 2 and "--report" in err and "not a directory" in err
    assert time.monotonic() - t0 < 10                   # no reconstruction ran
    assert (tmp_path / "plots").read_text() == "a file"


# ---- item 15: random bytes as .npz -------------------------------------------------------------------

def test_item15_random_npz_is_not_a_run_file(tmp_path, capsys):
    bad = tmp_path / "junk.npz"
    bad.write_bytes(np.random.default_rng(1).integers(0, 256, 4096, dtype=np.uint8).tobytes())
    code, err = exit_and_error(["reconstruct", bad], capsys)
    assert code == 2 and "junk.npz: not a shakerlab run file" in err and "pickle" not in err
    obj = tmp_path / "obj.npz"
    np.savez(obj, **{"linear/t": np.array([object(), 1], dtype=object)})
    code, err = exit_and_error(["reconstruct", obj], capsys)
    assert code == 2 and "not a shakerlab run file" in err and "allow_pickle" not in err


# ---- items 16 and 17: plausibility ----------------------------------------------------------------

@pytest.mark.slow
def test_item16_swapped_base_and_tip_warns_and_prints_folded_signs(run_copy, capsys):
    def swap(f):
        for name in f["entry/stages"]:
            g = f["entry/stages"][name]
            base, tip = g["x_base"][:], g["x_tip"][:]
            g["x_base"][:], g["x_tip"][:] = tip, base
    _edited(run_copy, swap)
    assert main(["reconstruct", str(run_copy), "--no-polish", "--json"]) == 0
    d = json.loads(capsys.readouterr().out)
    assert d["linear_step"]["c_m"] < 0 or d["linear_step"]["K_m"] < 0
    assert any("are base and tip swapped?" in w for w in d["warnings"])
    assert any("are base and tip swapped?" in w for w in d["linear_step"]["warnings"])
    assert {"parameters", "equation", "validation", "linear_step"} <= set(d)   # existing keys kept
    assert "+ -" not in d["equation"]
    assert main(["reconstruct", str(run_copy), "--no-polish"]) == 0
    text = capsys.readouterr().out
    assert "warning: linear step: negative" in text and "are base and tip swapped?" in text
    assert "+ -" not in text


def test_item16_equation_folds_signs():
    m = HystereticModel("base", c_m=-0.5, k_m=-32.7, alpha_m=-3.0, gamma=-2.0, delta=-1.0,
                        fn_m={"y^3": -4.0, "y*dy": 2.0})
    eq = m.equation()
    assert "+ -" not in eq and "- -" not in eq
    assert eq.startswith("y'' - 0.5 y' - 32.7 y - 4 y^3 + 2 y*y' + z = -x_base''")
    assert eq.endswith("z' = -3 y' + 2 |y'| z + 1 y' |z|")
    pos = HystereticModel("base", c_m=0.5, k_m=32.7, alpha_m=3.0, gamma=2.0, delta=1.0)
    assert pos.equation() == "y'' + 0.5 y' + 32.7 y + z = -x_base''\nz' = 3 y' - 2 |y'| z - 1 y' |z|"


def test_item17_stage_in_other_units_warns(run_file, tmp_path):
    assert run_warnings(load_run(run_file)) == []            # a consistent run: no warning
    for factor, stage in ((1000.0, "nonlinear"), (1e12, "validation")):
        path = tmp_path / f"x{factor:g}.h5"
        path.write_bytes(run_file.read_bytes())
        with h5py.File(path, "a") as f:
            g = f[f"entry/stages/{stage}"]
            for ch in ("x_base", "x_tip"):
                g[ch][:] = g[ch][:] * factor
        warnings = run_warnings(load_run(path))
        assert warnings and all("units?" in w for w in warnings)
        assert any(f"stage {stage!r}" in w for w in warnings)


@pytest.mark.slow
def test_item17_units_warning_reaches_the_cli(run_file, tmp_path, capsys):
    path = tmp_path / "mm.h5"
    path.write_bytes(run_file.read_bytes())
    with h5py.File(path, "a") as f:
        g = f["entry/stages/linear"]
        g["x_tip"][:] = g["x_tip"][:] * 1000.0          # one channel of one stage in mm
    before = digest(path)
    code = main(["diagnose", str(path), "--baseline", "linear", "--json"])
    out = capsys.readouterr().out
    assert code == 0, out
    assert any("units?" in w and "'linear'" in w for w in json.loads(out)["warnings"])
    assert digest(path) == before

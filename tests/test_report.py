"""`shakerlab report RUN.h5 -o DIR`: HTML + PNG + JSON, written back into the run file."""
import json
import re
from html import unescape

import h5py
import pytest

from workflows.batch import write_simulated_run
from recon.testing.truth import sdof_run
from shakerlab.cli import main
from shakerlab.runfile.results import read_results
from shakerlab.runfile.reader import save_npz


@pytest.fixture(scope="module")
def run_file(tmp_path_factory):
    d = tmp_path_factory.mktemp("report")
    truth = write_simulated_run(d / "run.h5", fs=1000.0, duration=4.0, seed=1)
    return d / "run.h5", truth


@pytest.mark.slow
def test_report_files_json_and_write_back(run_file, tmp_path, capsys):
    path, truth = run_file
    out = tmp_path / "rep"
    assert main(["report", str(path), "-o", str(out), "--json", "--resamples", "50", "--term-models", "5"]) == 0
    d = json.loads(capsys.readouterr().out)
    # the reconstruct JSON contract, extended
    for k in ("excitation", "parameters", "validation", "settings", "equation", "uncertainty", "report"):
        assert k in d
    assert {"window", "order", "noise_level"} <= set(d["settings"]["differentiation"])
    ts = d["term_selection"]                       # the bagged term selection (5 members)
    assert ts["available"] and ts["n_models"] == 5 and ts["selected"] == sorted(truth.fn_m)
    assert all(ts["inclusion"][t] >= 0.8 for t in truth.fn_m)
    assert set(d["parameters"]["fn_m"]) == set(truth.fn_m)
    iv = d["uncertainty"]["intervals"]
    for k in ("c_m", "k_m", "alpha_m", "gamma", "delta"):
        assert iv[k][0] < d["parameters"][k] < iv[k][1]
    for term in truth.fn_m:
        assert iv["fn_m"][term][0] < d["parameters"]["fn_m"][term] < iv["fn_m"][term][1]
    # files: self-contained HTML (every figure embedded) + PNGs + JSON
    pngs = sorted(p.name for p in out.glob("*.png"))
    assert pngs == ["loops.png", "residual.png", "restoring_force.png", "stages.png", "validation_validation.png"]
    assert all((out / p).stat().st_size > 10_000 for p in pngs)
    html = unescape((out / "index.html").read_text())
    assert len(re.findall(r"src='data:image/png;base64,", html)) == len(pngs)
    assert "src='" not in html.replace("src='data:", "")          # nothing loaded from outside
    for text in ("Recorded stages", "Differentiation", "z' =", "95 % intervals", "kernel cluster",
                 "hysteresis loops", "Residual", "linear", "nonlinear", "validation"):
        assert text.lower() in html.lower(), text
    assert json.loads((out / "result.json").read_text())["parameters"] == d["parameters"]
    # written back: a new result group with the settings hash; raw data untouched
    assert d["report"]["result_group"] == "reconstruction_000"
    stored = read_results(path)["reconstruction_000"]
    assert stored["parameters"] == d["parameters"]
    assert stored["uncertainty"]["intervals"] == d["uncertainty"]["intervals"]
    with h5py.File(path, "r") as f:
        g = f["entry/results/reconstruction_000"]
        assert g.attrs["settings_hash"] == d["reprocess"]["settings_hash"]
        assert g.attrs["software_version"]
        assert f["entry/stages/nonlinear/x_tip"].shape[0] == 4001

    # same settings again: nothing new written, said so
    assert main(["report", str(path), "-o", str(tmp_path / "rep2"), "--resamples", "50", "--term-models", "5"]) == 0
    cap = capsys.readouterr()
    assert "nothing new written" in cap.out and "intervals" in cap.out and "report:" in cap.out
    assert "reconstructing run.h5" in cap.err and "done in" in cap.err     # progress on stderr
    assert list(read_results(path)) == ["reconstruction_000"]
    # other settings: a second group
    assert main(["report", str(path), "-o", str(tmp_path / "rep3"), "--no-polish", "--no-uncertainty", "--term-models", "0",
                 "--json"]) == 0
    d3 = json.loads(capsys.readouterr().out)
    assert "uncertainty" not in d3 and "term_selection" not in d3
    assert d3["report"]["result_group"] == "reconstruction_001"


def test_report_refuses_and_notes(tmp_path, capsys):
    run, _ = sdof_run("base", snr_db=80.0, fs=1000.0, duration=4.0, seed=1)
    npz = tmp_path / "run.npz"
    save_npz(run, npz)
    assert main(["report", str(npz), "-o", str(tmp_path / "r"), "--no-uncertainty", "--no-polish", "--term-models", "0",
                 "--json"]) == 0
    assert "only .h5 run files hold results" in json.loads(capsys.readouterr().out)["report"]["note"]
    unclean = tmp_path / "unclean.h5"
    write_simulated_run(unclean, fs=1000.0, duration=4.0, seed=1)
    with h5py.File(unclean, "a") as f:
        f.attrs["clean_close"] = False
    assert main(["report", str(unclean), "-o", str(tmp_path / "u"), "--no-uncertainty", "--no-polish",
                 "--term-models", "0"]) == 0
    assert "not closed cleanly" in capsys.readouterr().out
    with h5py.File(unclean, "r") as f:
        assert len(f["entry/results"]) == 0
    assert main(["report", str(tmp_path / "none.h5"), "-o", str(tmp_path / "x")]) == 2
    assert "no such file" in capsys.readouterr().err
    (tmp_path / "file").write_text("")
    assert main(["report", str(unclean), "-o", str(tmp_path / "file")]) == 2
    assert "is not a directory" in capsys.readouterr().err
    assert main(["report", str(unclean), "-o", str(tmp_path / "y"), "--resamples", "3"]) == 2
    assert "--resamples must be at least 50" in capsys.readouterr().err
    assert main(["report", str(unclean), "-o", str(tmp_path / "y"), "--term-models", "2"]) == 2
    assert "--term-models must be 0 (off) or at least 5" in capsys.readouterr().err


def test_reconstruct_uncertainty_flag(run_file, capsys):
    path, _ = run_file
    assert main(["reconstruct", str(path), "--no-polish"]) == 0
    assert "intervals" not in capsys.readouterr().out
    assert main(["reconstruct", str(path), "--uncertainty"]) == 0
    out = capsys.readouterr().out
    assert "95 % intervals (200 ensemble members)" in out and "fn_m[y^3]" in out and "1/(m^2*s^2)" in out

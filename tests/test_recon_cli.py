"""`shakerlab reconstruct RUN.npz --json` on a run written by the test."""
import json

import pytest

from recon.testing.truth import sdof_run
from shakerlab.cli import main
from shakerlab.runfile.reader import save_npz
from helpers import check_weak_form_at_40db


@pytest.fixture(scope="module")
def run_file(tmp_path_factory):
    path = tmp_path_factory.mktemp("recon") / "run.npz"
    run, truth = sdof_run("base", snr_db=80.0, seed=7)
    save_npz(run, path)
    return path, truth


@pytest.mark.slow
def test_reconstruct_json(run_file, capsys, tmp_path):
    path, truth = run_file
    assert main(["reconstruct", str(path), "--json", "--plots", str(tmp_path / "png"),
                 "--save-model", str(tmp_path / "model.json")]) == 0
    d = json.loads(capsys.readouterr().out)
    assert d["excitation"] == "base"
    for k in ("c_m", "k_m", "alpha_m", "gamma", "delta", "fn_m"):
        assert k in d["parameters"]
    assert "inv_m" not in d["parameters"]
    assert set(d["parameters"]["fn_m"]) == set(truth.fn_m)
    assert d["validation"]["stage"] == "validation" and d["validation"]["nrmse"] < 0.01
    s = d["settings"]
    assert {"window", "order", "noise_level"} <= set(s["differentiation"])
    assert s["library_order"] == 5 and s["threshold"] > 0
    pngs = list((tmp_path / "png").glob("*.png"))
    assert len(pngs) == 2 and all(p.stat().st_size > 10_000 for p in pngs)
    assert json.loads((tmp_path / "model.json").read_text())["parameters"]["k_m"] == d["parameters"]["k_m"]


@pytest.fixture(scope="module")
def short_file(tmp_path_factory):
    """4 s at 1 kHz: enough for the text output's lines (the 10 s run is for the JSON's accuracy)."""
    path = tmp_path_factory.mktemp("recon_short") / "short.npz"
    run, _ = sdof_run("base", snr_db=80.0, seed=7, duration=4.0, fs=1000.0)
    save_npz(run, path)
    return path


def test_reconstruct_text_and_order(short_file, capsys):
    path = short_file
    assert main(["reconstruct", str(path), "--library-order", "3", "--no-polish"]) == 0
    out = capsys.readouterr().out
    assert "z' =" in out and "validation NRMSE" in out and "window" in out


def test_reconstruct_bad_input(tmp_path, capsys):
    assert main(["reconstruct", str(tmp_path / "none.npz")]) == 2
    assert "no such file" in capsys.readouterr().err
    bad = tmp_path / "bad.npz"
    bad.write_bytes(b"not a zip")
    assert main(["reconstruct", str(bad), "--json"]) == 2
    assert "bad.npz: not a shakerlab run file" in capsys.readouterr().err  # issue 15 item 15


def test_reconstruct_weak_form_at_40db(tmp_path, capsys):
    # --form weak: the form that holds at 40 dB (docs/method.md); the JSON says which form ran
    path = tmp_path / "run40.npz"
    run, truth = sdof_run("base", snr_db=40.0, seed=1)
    save_npz(run, path)
    assert main(["reconstruct", str(path), "--json", "--form", "weak"]) == 0
    d = json.loads(capsys.readouterr().out)
    assert d["settings"]["form"] == "weak"
    # the record is test_recon_weak_path.py's seed 1: its accuracy checks, made here on the JSON
    check_weak_form_at_40db(d["parameters"], d["nonlinear_step"]["hysteresis"]["path_form"]["rows"], truth)
    with pytest.raises(SystemExit) as exc:           # argparse names the allowed forms
        main(["reconstruct", str(path), "--form", "nonsense"])
    assert exc.value.code == 2 and "invalid choice" in capsys.readouterr().err

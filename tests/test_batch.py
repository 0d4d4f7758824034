"""`shakerlab reprocess`: a batch of simulated run files on a real local Dask cluster.

Among the runs: a truncated (corrupted) HDF5 file, a run without its linear stage,
a file that is not a run file and a run that was not closed cleanly. The cluster
is a real dask.distributed LocalCluster with 2 worker *processes*.
"""
import csv

import h5py
import numpy as np
import pytest

from workflows.batch import (BatchSettings, expand, format_table, process_run, run_batch, settings_hash, write_csv,
                         write_simulated_run)
from recon import ReconSettings, reconstruct
from recon.output_error.uncertainty import UncertaintySettings, parameter_intervals
from shakerlab.cli import main
from shakerlab.errors import UserFacingError
from shakerlab.runfile.results import read_results
from shakerlab.runfile.reader import load_run

FAST = {"n_resamples": 50}
GOOD = ("run_a.h5", "run_b.h5")


@pytest.fixture(scope="module")
def batch_dir(tmp_path_factory):
    d = tmp_path_factory.mktemp("batch")
    truths = {}
    for seed, name in enumerate(GOOD):
        truths[name] = write_simulated_run(d / name, fs=1000.0, duration=4.0, seed=seed)
    write_simulated_run(d / "no_linear.h5", fs=1000.0, duration=4.0, seed=3, stages=("nonlinear", "validation"))
    (d / "corrupt.h5").write_bytes((d / "run_a.h5").read_bytes()[:6000])
    with h5py.File(d / "other.h5", "w") as f:
        f["data"] = np.arange(10.0)
    write_simulated_run(d / "unclean.h5", fs=1000.0, duration=4.0, seed=0)
    with h5py.File(d / "unclean.h5", "a") as f:      # as a crashed recording leaves it
        f.attrs["clean_close"] = False
    return d, truths


def _paths(d):
    return [str(p) for p in sorted(d.glob("*.h5"))]


@pytest.mark.slow
def test_batch_on_local_cluster(batch_dir, capsys):
    d, truths = batch_dir
    paths = _paths(d)
    s = BatchSettings(workers=2, processes=True, uncertainty_settings=FAST)
    rows = run_batch(paths, s)
    by = {r["run"].rsplit("/", 1)[-1]: r for r in rows}
    assert [r["run"] for r in rows] == paths
    # bad ones: clear reasons, the batch went on
    assert by["corrupt.h5"]["status"] == "failed"
    assert "not a readable HDF5 file" in by["corrupt.h5"]["reason"] and "corrupt.h5" in by["corrupt.h5"]["reason"]
    assert by["no_linear.h5"]["status"] == "failed"
    assert "no stage 'linear'" in by["no_linear.h5"]["reason"]
    assert by["other.h5"]["status"] == "failed" and "not a shakerlab run file" in by["other.h5"]["reason"]
    # unclean: processed, never written
    assert by["unclean.h5"]["status"] == "ok" and not by["unclean.h5"]["written"]
    assert any("not closed cleanly" in n for n in by["unclean.h5"]["notes"])
    # good ones: identical to the single-run result computed here, in this process
    for name in GOOD:
        row = by[name]
        assert row["status"] == "ok" and row["written"], row
        run = load_run(d / name)
        single = reconstruct(run, ReconSettings())
        ref = single.to_dict()["parameters"]
        assert row["parameters"]["fn_m"] == ref["fn_m"]
        for k in ("c_m", "k_m", "alpha_m", "gamma", "delta"):
            assert row["parameters"][k] == ref[k]
        unc = parameter_intervals(single.model, run, UncertaintySettings(**FAST))
        assert row["intervals"]["k_m"] == unc["intervals"]["k_m"]
        # and close to the truth (80 dB)
        true_p = truths[name].to_dict()["parameters"]
        assert set(ref["fn_m"]) == set(true_p["fn_m"])
        assert abs(ref["k_m"] / true_p["k_m"] - 1) < 0.02
        # written back with the settings hash
        stored = read_results(d / name)
        assert list(stored) == ["reconstruction_000"]
        assert stored["reconstruction_000"]["reprocess"]["settings_hash"] == settings_hash(s.job())
        with h5py.File(d / name, "r") as f:
            assert f["entry/results/reconstruction_000"].attrs["settings_hash"] == settings_hash(s.job())
            assert f["entry/stages/linear/x_tip"].shape[0] == 4001      # raw data untouched
    # the summary: printed table and CSV
    table = format_table(rows)
    assert "failed runs:" in table and "no stage 'linear'" in table and "run_a.h5" in table
    out = write_csv(rows, d / "summary.csv")
    lines = list(csv.DictReader(out.open()))
    assert [l["status"] for l in lines] == [r["status"] for r in rows]
    a = next(l for l in lines if l["run"].endswith("run_a.h5"))
    assert float(a["k_m_low"]) < float(a["k_m"]) < float(a["k_m_high"])
    assert float(a["fn_m[y^3]"]) == by["run_a.h5"]["parameters"]["fn_m"]["y^3"]

    # re-running with the same settings skips the processed runs (plain loop, same rows)
    again = {r["run"].rsplit("/", 1)[-1]: r for r in run_batch(paths, s)}
    for name in GOOD:
        assert again[name]["status"] == "skipped"
        assert again[name]["parameters"] == by[name]["parameters"]
        assert list(read_results(d / name)) == ["reconstruction_000"]
    assert again["corrupt.h5"]["status"] == "failed"
    assert again["unclean.h5"]["status"] == "ok"        # nothing stored, so processed again
    # other settings: processed again, a new group
    other = process_run(str(d / "run_a.h5"), BatchSettings(recon={"no_such": 1}).job())
    assert other["status"] == "failed" and "no_such" in other["reason"]
    row = process_run(str(d / "run_a.h5"), BatchSettings(recon={"polish": False}, uncertainty=False).job())
    assert row["status"] == "ok" and row["group"] == "reconstruction_001" and row["intervals"] == {}


def test_reprocess_cli_serial_and_errors(batch_dir, tmp_path, capsys):
    d, _ = batch_dir
    csv_path = tmp_path / "s.csv"
    rc = main(["reprocess", str(d / "run_*.h5"), str(d / "no_linear.h5"), "--serial", "--resamples", "50",
               "--csv", str(csv_path), "--no-write-back"])
    cap = capsys.readouterr()
    assert rc == 1                       # one run failed
    assert "no stage 'linear'" in cap.out and "run_b.h5" in cap.out
    assert "run 3 of 3 done" in cap.err    # progress on stderr
    assert csv_path.exists() and len(csv_path.read_text().splitlines()) == 4
    assert main(["reprocess", str(d / "nothing_*.h5")]) == 2
    assert "no run file matches" in capsys.readouterr().err
    assert main(["reprocess", str(d / "run_a.h5"), "--workers", "0"]) == 2
    assert "--workers must be at least 1" in capsys.readouterr().err
    with pytest.raises(UserFacingError, match="--scheduler tcp://127.0.0.1:9: cannot connect"):
        run_batch([str(d / "run_a.h5")], BatchSettings(scheduler="tcp://127.0.0.1:9", connect_timeout=0.2))


def test_diagnose_unavailable_is_said(batch_dir, monkeypatch):
    import workflows.batch as batch

    d, _ = batch_dir
    monkeypatch.setattr(batch, "diagnosis_available", lambda: False)
    row = process_run(str(d / "run_b.h5"), BatchSettings(diagnose=True, uncertainty=False, write_back=False,
                                                         recon={"polish": False}).job())
    assert row["status"] == "ok" and row["diagnosis"] == "unavailable"
    assert any("diagnosis unavailable" in n for n in row["notes"])


def test_expand_patterns(tmp_path):
    for n in ("b.h5", "a.h5"):
        (tmp_path / n).write_bytes(b"")
    assert expand([str(tmp_path / "*.h5"), str(tmp_path / "a.h5")]) == [str(tmp_path / "a.h5"), str(tmp_path / "b.h5")]
    with pytest.raises(UserFacingError, match="no run file matches"):
        expand([str(tmp_path / "*.npz")])


def test_drive_leaves_earlier_settings_hashes_as_they_were_and_is_a_row_on_a_base_run(batch_dir):
    import hashlib
    import json as _json

    from recon.output_error.uncertainty import UncertaintySettings
    from shakerlab import __version__

    d, _ = batch_dir
    job = BatchSettings(recon={"library_order": 5, "polish": True}).job()
    # the hash of a job without --drive is the one the same job had before the setting existed
    rs = {k: v for k, v in ReconSettings(**job["recon"]).to_dict().items() if k != "drive"}
    text = _json.dumps({"recon": rs, "uncertainty": UncertaintySettings(**job.get("uncertainty_settings", {})).to_dict(),
                        "software": __version__}, sort_keys=True, default=str)
    assert settings_hash(job) == hashlib.sha256(text.encode()).hexdigest()[:16]
    driven = BatchSettings(recon={"library_order": 5, "polish": True, "drive": True}, uncertainty=False,
                           write_back=False).job()
    assert settings_hash(driven) != settings_hash(BatchSettings(recon={"library_order": 5, "polish": True},
                                                                uncertainty=False, write_back=False).job())
    row = process_run(str(d / "run_a.h5"), driven)      # a base-excitation run: a failed row with the reason
    assert row["status"] != "ok" and "--drive needs force excitation" in row["reason"], row

"""bench/diagnose.py --stress keeps saved rows: --jsonl never truncates a file, --from-jsonl joins files."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _bench(*args, cwd):
    return subprocess.run([sys.executable, str(ROOT / "bench" / "diagnose.py"), "--stress", *args],
                          cwd=cwd, capture_output=True, text=True, timeout=120)


def test_jsonl_refuses_an_existing_file_and_leaves_it_as_it_was(tmp_path):
    saved = tmp_path / "rows.jsonl"
    saved.write_text('{"index": 0}\n')
    p = _bench("--n", "1", "--jsonl", str(saved), cwd=tmp_path)
    assert p.returncode != 0
    assert "exists" in p.stderr and str(saved) in p.stderr
    assert saved.read_text() == '{"index": 0}\n'


def test_from_jsonl_joins_files_by_index_and_refuses_files_without_rows(tmp_path):
    row = {"index": 3, "effect": "none", "protocol": "paper", "status": "ok", "first": "none", "named": [],
           "right": True, "strength": 1.0, "held_out": {}, "seconds": 1.0, "sim_seconds": 1.0}
    a, b, empty = tmp_path / "a.jsonl", tmp_path / "b.jsonl", tmp_path / "empty.jsonl"
    a.write_text(json.dumps({**row, "right": False, "first": "offset", "named": ["offset"]}) + "\n")
    b.write_text(json.dumps(row) + "\n")
    empty.write_text("\n")
    p = _bench("--from-jsonl", str(a), str(b), cwd=tmp_path)
    assert p.returncode == 0, p.stderr
    assert "1 saved rows" in p.stdout and "false alarms on clean recordings: 0/1" in p.stdout
    p = _bench("--from-jsonl", str(empty), cwd=tmp_path)
    assert p.returncode != 0 and "no rows" in p.stderr


def test_from_jsonl_keeps_blocks_apart_by_index_and_in_the_table(tmp_path):
    # random row #0 and pair row #0 are two recordings: both kept, each counted in its own table
    row = {"index": 0, "effect": "none", "protocol": "paper", "status": "ok", "first": "none", "named": [],
           "right": True, "strength": 1.0, "held_out": {}, "seconds": 1.0, "sim_seconds": 1.0}
    pair = {**row, "block": "pairs", "effect": "higher_mode", "also": [["coulomb_friction", 0.7]],
            "first": "sensor_scale", "named": ["sensor_scale", "coulomb_friction"], "right": False}
    a = tmp_path / "a.jsonl"
    a.write_text(json.dumps(row) + "\n" + json.dumps(pair) + "\n")
    p = _bench("--from-jsonl", str(a), cwd=tmp_path)
    assert p.returncode == 0, p.stderr
    assert "2 saved rows" in p.stdout
    random_part, pair_part = p.stdout.split("== two effects concealed together: 1 rows ==")
    assert "false alarms on clean recordings: 0/1" in random_part and "sensor_scale" not in random_part
    assert "| higher_mode + coulomb_friction | 1 |" in pair_part
    assert "one of the two concealed effects named first: 0/1" in pair_part and "both named: 0/1" in pair_part


def _recon_row(seed, snr, c_m, fn, worst):
    return {"seed": seed, "snr": snr, "protocol": "paper", "fs": 2000.0, "status": "ok", "exact": True,
            "worst": worst, "worst_param": "c_m", "spurious": [], "missed": [], "seconds": 1.0,
            "system": {"f_n": 20.0}, "result": {"c_m": c_m, "k_m": 1000.0, "fn_m": fn}}


def test_recon_stress_against_counts_the_same_answers_and_names_each_other(tmp_path):
    ref, new = tmp_path / "ref.jsonl", tmp_path / "new.jsonl"
    ref.write_text("".join(json.dumps(r) + "\n" for r in (
        _recon_row(1, 80.0, 2.0, {"y^2": 5.0}, 0.001), _recon_row(2, 80.0, 2.0, {"y^2": 5.0}, 0.001),
        _recon_row(3, 80.0, 2.0, {"y^2": 5.0}, 0.001))))
    new.write_text("".join(json.dumps(r) + "\n" for r in (
        _recon_row(1, 80.0, 2.0 * (1 + 1e-8), {"y^2": 5.0}, 0.001),      # the same within 1e-6
        _recon_row(2, 80.0, 2.2, {"y^2": 5.0}, 0.1),                     # moved 10 %
        _recon_row(3, 80.0, 2.0, {"y^3": 5.0}, 0.001),                   # other terms
        _recon_row(4, 80.0, 2.0, {"y^2": 5.0}, 0.001))))                 # not stored
    p = subprocess.run([sys.executable, str(ROOT / "bench" / "recon_accuracy.py"), "--stress", "--snr", "80",
                        "--from-jsonl", str(new), "--against", str(ref)],
                       cwd=tmp_path, capture_output=True, text=True, timeout=120)
    assert p.returncode == 0, p.stderr
    assert "against the stored rows: 1 of 3 the same" in p.stdout and "1 not in them" in p.stdout
    assert "seed 2 80 dB paper: parameters moved 0.1" in p.stdout
    assert "seed 3 80 dB paper: parameters moved inf" in p.stdout


def test_recon_stress_jsonl_refuses_an_existing_file_and_leaves_it_as_it_was(tmp_path):
    saved = tmp_path / "rows.jsonl"
    saved.write_text('{"seed": 0}\n')
    p = subprocess.run([sys.executable, str(ROOT / "bench" / "recon_accuracy.py"), "--stress", "--seeds", "1",
                        "--jsonl", str(saved)], cwd=tmp_path, capture_output=True, text=True, timeout=120)
    assert p.returncode != 0 and "exists" in p.stderr
    assert saved.read_text() == '{"seed": 0}\n'


def test_rig_discovery_refuses_a_validation_factor_out_of_range_or_beside_a_protocol(tmp_path):
    """bench/rig_discovery.py --validation-factor changes the short protocol: a value outside 0.2-2
    times the resonance, or one given with --protocol (whose stages it would not change), is refused
    with the option named, before anything is simulated."""
    def run(*args):
        return subprocess.run([sys.executable, str(ROOT / "bench" / "rig_discovery.py"), "--effects", "clean",
                               *args], cwd=tmp_path, capture_output=True, text=True, timeout=120)

    p = run("--validation-factor", "5")
    assert p.returncode == 2 and "--validation-factor 5.0 is outside 0.2-2" in p.stderr, p.stderr
    proto = tmp_path / "p.toml"
    proto.write_text("")
    p = run("--validation-factor", "0.78", "--protocol", str(proto))
    assert p.returncode == 2 and "do not apply to --protocol" in p.stderr, p.stderr
    assert not list(tmp_path.glob("*.h5"))

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

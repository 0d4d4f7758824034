"""Under --json every refusal is one JSON object on stdout (with the error), the message stays on stderr and
the exit status is 2 (issue 74)."""
import json
import os
import subprocess
import sys

import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def shakerlab(*argv):
    env = dict(os.environ, PYTHONPATH=ROOT)
    return subprocess.run([sys.executable, "-m", "shakerlab.cli", *argv], capture_output=True, text=True,
                          env=env, timeout=120)


@pytest.mark.parametrize("command", ["reconstruct", "diagnose", "report"])
def test_refusal_is_one_json_object(tmp_path, command):
    bad = tmp_path / "bad.npz"
    bad.write_bytes(b"not a zip")
    argv = [command, str(bad), "--json"] + (["-o", str(tmp_path / "out")] if command == "report" else [])
    p = shakerlab(*argv)
    assert p.returncode == 2, p.stderr
    d = json.loads(p.stdout)                      # one object, nothing else on stdout
    assert isinstance(d, dict) and "not a shakerlab run file" in d["error"]
    assert d["command"] == command and d["exit_code"] == 2
    assert "error: " in p.stderr and "not a shakerlab run file" in p.stderr


def test_refusal_without_json_keeps_stdout_empty(tmp_path):
    bad = tmp_path / "bad.npz"
    bad.write_bytes(b"not a zip")
    p = shakerlab("diagnose", str(bad))
    assert p.returncode == 2 and p.stdout == "" and "not a shakerlab run file" in p.stderr

import subprocess
import sys

import numpy as np
import pytest

from shakerlab import __version__
from shakerlab.cli import main
from shakerlab.errors import UserFacingError
from shakerlab.run_data import Run, Stage
from shakerlab.runfile.reader import load_run, save_npz


def test_version_from_console_script():
    out = subprocess.run(
        [sys.executable, "-m", "shakerlab.cli", "--version"], capture_output=True, text=True, check=True
    )
    assert out.stdout.strip() == f"shakerlab {__version__}"


def test_no_command_prints_help(capsys):
    assert main([]) == 2
    assert "usage: shakerlab" in capsys.readouterr().out


def test_npz_round_trip(tmp_path):
    t = np.arange(100) / 1000.0
    run = Run({"linear": Stage("linear", t, {"x_base": np.sin(t), "x_tip": np.cos(t)})})
    save_npz(run, tmp_path / "r.npz")
    back = load_run(tmp_path / "r.npz")
    assert list(back.stages) == ["linear"]
    np.testing.assert_array_equal(back.stage("linear").y, np.cos(t) - np.sin(t))
    assert back.excitation == "base"


def test_stage_rejects_bad_input():
    t = np.arange(10.0)
    with pytest.raises(UserFacingError, match="lacks channel"):
        Stage("s", t, {"x_tip": t})
    with pytest.raises(UserFacingError, match="non-finite value at sample 3"):
        Stage("s", t, {"x_base": t, "x_tip": np.where(t == 3, np.nan, t)})
    with pytest.raises(UserFacingError, match="no stage 'nonlinear'"):
        Run({}, source="x.npz").stage("nonlinear")

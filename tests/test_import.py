"""`shakerlab import`: CSV stage files -> run file; bad files name line and column."""
import numpy as np
import pytest

from shakerlab.cli import main
from shakerlab.errors import UserFacingError
from shakerlab.import_command import import_csv
from shakerlab.runfile.reader import load_run


def _csv(path, header, cols):
    lines = [header] + [",".join(repr(float(v)) for v in row) for row in np.column_stack(cols)]
    path.write_text("\n".join(lines) + "\n")
    return path


def test_import_base_excitation_cli(tmp_path, capsys):
    t = np.arange(200) / 500.0
    lin = _csv(tmp_path / "lin.csv", "t,x_base,x_tip", [t + 3.0, np.sin(t), 2 * np.sin(t)])
    non = _csv(tmp_path / "non.csv", "# exported by foo\nt, x_base, x_tip", [t, np.cos(t), 3 * np.cos(t)])
    out = tmp_path / "run.h5"
    assert main(["import", "-o", str(out), "--linear", str(lin), "--nonlinear", str(non)]) == 0
    assert "linear: 200 samples at 500 Hz" in capsys.readouterr().out
    run = load_run(out)
    assert run.excitation == "base"
    np.testing.assert_allclose(run.stage("linear").t, t, atol=1e-12)
    np.testing.assert_allclose(run.stage("nonlinear").y, 2 * np.cos(t))
    assert run.stage("linear").settings["source_t0"] == 3.0


def test_import_force_excitation(tmp_path):
    t = np.arange(50) / 100.0
    f = _csv(tmp_path / "f.csv", "t,force,x", [t, np.sin(t), np.cos(t)])
    run = load_run(import_csv(tmp_path / "r.h5", {"linear": f}))
    assert run.excitation == "force"
    np.testing.assert_allclose(run.stage("linear").y, np.cos(t))


@pytest.mark.parametrize("text, match", [
    ("t,x_base,x_tip\n0,1,2\n0.1,abc,2\n", r"line 3, column 2 \(x_base\): 'abc' is not a number"),
    ("t,x_base,x_tip\n0,1,2\n0.1,1\n", r"line 3: 2 column\(s\), the header has 3"),
    ("t,x_base,x_tip\n0,1,2\n0,1,2\n", r"line 3, column 1 \(t\): time 0 does not increase"),
    ("t,x_base,x_tip\n0,1,2\n1,1,nan\n", r"line 3, column 3 \(x_tip\): value 'nan' is not finite"),
    ("time,a,b\n0,1,2\n", r"line 1: header is 'time,a,b'"),
    ("", r"empty file"),
])
def test_bad_files_name_line_and_column(tmp_path, text, match):
    bad = tmp_path / "bad.csv"
    bad.write_text(text)
    with pytest.raises(UserFacingError, match=match):
        import_csv(tmp_path / "r.h5", {"linear": bad})
    assert not (tmp_path / "r.h5").exists()


def test_cli_errors(tmp_path, capsys):
    t = np.arange(10.0)
    a = _csv(tmp_path / "a.csv", "t,x_base,x_tip", [t, t, t])
    b = _csv(tmp_path / "b.csv", "t,force,x", [t, t, t])
    assert main(["import", "-o", str(tmp_path / "r.h5"), "--linear", str(a), "--nonlinear", str(b)]) == 2
    assert "mix excitation kinds" in capsys.readouterr().err
    assert main(["import", "-o", str(tmp_path / "r.h5")]) == 2
    assert "nothing to import" in capsys.readouterr().err
    assert main(["import", "-o", str(tmp_path / "r.h5"), "--linear", str(tmp_path / "nope.csv")]) == 2
    assert "nope.csv: no such file" in capsys.readouterr().err


@pytest.mark.parametrize("suffix, opener", [(".csv.gz", "gzip"), (".csv.bz2", "bz2"), (".csv.xz", "lzma")])
def test_import_compressed_csv(tmp_path, capsys, suffix, opener):
    """A CSV compressed whole is imported as the plain one; a corrupt one is a one-line error."""
    import importlib
    t = np.arange(300) / 1000.0
    plain = _csv(tmp_path / "non.csv", "t,x_base,x_tip", [t, np.sin(40 * t), 2 * np.sin(40 * t)])
    packed = tmp_path / f"non{suffix}"
    with importlib.import_module(opener).open(packed, "wb") as fh:
        fh.write(plain.read_bytes())
    out = tmp_path / "run.h5"
    assert main(["import", "-o", str(out), "--nonlinear", str(packed)]) == 0
    assert "nonlinear: 300 samples at 1000 Hz" in capsys.readouterr().out
    np.testing.assert_allclose(load_run(out).stage("nonlinear").y, np.sin(40 * t))
    bad = tmp_path / f"bad{suffix}"
    bad.write_bytes(b"not compressed at all")
    assert main(["import", "-o", str(tmp_path / "bad.h5"), "--nonlinear", str(bad)]) == 2
    err = [ln for ln in capsys.readouterr().err.strip().splitlines() if not ln.startswith("[")]   # less progress
    assert len(err) == 1 and f"bad{suffix}: cannot read as a text CSV file" in err[0]


def test_import_shows_its_progress_on_stderr_and_keeps_stdout(tmp_path):
    """`import` tells each stage as it reads and writes it on stderr (a large file takes a while);
    stdout keeps its lines; --quiet shows nothing."""
    import subprocess
    import sys

    t = np.arange(20000) / 1000.0
    csv = tmp_path / "lin.csv"
    np.savetxt(csv, np.column_stack([t, 1e-3 * np.sin(7 * t), 2e-3 * np.sin(7 * t)]), delimiter=",",
               header="t,x_base,x_tip", comments="")
    for quiet in (False, True):
        out = tmp_path / f"run{int(quiet)}.h5"
        r = subprocess.run([sys.executable, "-m", "shakerlab.cli", "import", "-o", str(out), "--linear", str(csv)]
                           + (["--quiet"] if quiet else []), capture_output=True, text=True, timeout=120)
        assert r.returncode == 0, r.stderr
        assert r.stdout.splitlines() == ["linear: 20000 samples at 1000 Hz", f"wrote {out}"]
        if quiet:
            assert r.stderr == ""
        else:
            assert "reading stage linear from lin.csv" in r.stderr
            assert "writing stage linear (20000 samples)" in r.stderr
            assert r.stderr.rstrip().splitlines()[-1].startswith("imported in ")

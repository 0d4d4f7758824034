"""Issue 69: ten ways a user could lose data, leak a write or get a traceback, each reproduced.

Real run files, real CLI runs (in this process through ``shakerlab.cli.main``, or as a separate process
where a signal or a kill is the point), a real full file system (a small tmpfs mounted here when the
test runs as root). Every test checks the exit status, the one-line message, that no file other than
the asked output changed (sha256 of every file before and after) and that nothing temporary is left.
"""
import errno
import hashlib
import os
import re
import signal
import subprocess
import sys
import time
import tracemalloc
from pathlib import Path

import h5py
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings, strategies as st

from shakerlab.cli import main
from shakerlab.errors import UserFacingError
from shakerlab.output_files import OutputLock, inside
from shakerlab.run_data import check_stage_name
from shakerlab.runfile.reader import read_info, read_run
from shakerlab.runfile.results import add_result, read_results, store_result
from workflows.batch import write_simulated_run

from test_rig_acquisition import SMALL_PROTOCOL

ROOT = Path(__file__).resolve().parents[1]
TEMPORARY = (".partial", ".lock", ".tmp")


def tree(d) -> dict:
    """{relative path: sha256} of every file under ``d`` (symbolic links by their target text)."""
    out = {}
    for p in sorted(Path(d).rglob("*")):
        rel = str(p.relative_to(d))
        if p.is_symlink():
            out[rel] = "-> " + os.readlink(p)
        elif p.is_file():
            out[rel] = hashlib.sha256(p.read_bytes()).hexdigest()
    return out


def leftovers(d) -> list:
    return [n for n in tree(d) if any(t in n for t in TEMPORARY)]


def cli(argv, capsys):
    code = main([str(a) for a in argv])
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def one_line(err: str) -> str:
    """The one error line of a failed command (the progress lines it printed before are not part
    of the message)."""
    lines = [ln for ln in err.strip().splitlines() if ln.strip() and not re.match(r"\[\s*\d+ %\]", ln)]
    assert len(lines) == 1, err
    assert "Traceback" not in err
    return lines[0]


def _csv(path, n=200):
    t = np.arange(n) / 500.0
    with open(path, "w") as fh:
        fh.write("t,x_base,x_tip\n")
        np.savetxt(fh, np.column_stack([t, np.sin(t), 2 * np.sin(t)]), delimiter=",", fmt="%.17g")
    return path


def _env():
    return dict(os.environ, PYTHONPATH=os.pathsep.join([str(ROOT), str(ROOT / "tests")]), PYTHONUNBUFFERED="1")


@pytest.fixture(scope="module")
def run_file(tmp_path_factory):
    d = tmp_path_factory.mktemp("faults")
    write_simulated_run(d / "run.h5", fs=500.0, duration=2.0, seed=3)
    return d / "run.h5"


@pytest.fixture
def run_copy(run_file, tmp_path):
    path = tmp_path / "run.h5"
    path.write_bytes(run_file.read_bytes())
    return path


# ---- 1: a stage name from a file never becomes a path ------------------------------------------------

def test_issue69_1_stage_name_with_dotdot_is_refused_at_load(tmp_path, capsys):
    work = tmp_path / "work"
    work.mkdir()
    (tmp_path / "OUTSIDE.png").write_bytes(b"someone's figure")
    t = np.arange(400) / 100.0
    arrays = {}
    for stage in ("linear", "nonlinear", "validation/../../OUTSIDE"):
        arrays.update({f"{stage}_t": t, f"{stage}_x_base": 1e-3 * np.sin(t), f"{stage}_x_tip": 2e-3 * np.sin(t)})
    np.savez(work / "evil.npz", **arrays)
    before = tree(tmp_path)
    code, out, err = cli(["reconstruct", work / "evil.npz", "-o", work / "plots"], capsys)
    assert code == 2
    assert "stage name 'validation/../../OUTSIDE' is not a plain name" in one_line(err)
    assert tree(tmp_path) == before and not (work / "plots").exists()
    # the same name in an HDF5 run file
    h5 = work / "evil.h5"
    write_simulated_run(h5, fs=200.0, duration=1.0, seed=1)
    with h5py.File(h5, "a") as f:
        f["entry/stages"].move("validation", "..")
    before = tree(tmp_path)
    code, out, err = cli(["reconstruct", h5, "-o", work / "plots"], capsys)
    assert code == 2 and "stage name '..' is not a plain name" in one_line(err)
    assert tree(tmp_path) == before
    # every output path built from a name stays in the folder given
    with pytest.raises(UserFacingError, match="outside"):
        inside(work, "../OUTSIDE", ".png")


# ---- 2: the lock file is never followed through a symbolic link --------------------------------------

def test_issue69_2_lock_file_symlink_is_refused(tmp_path, capsys):
    victim = tmp_path / "victim.txt"
    victim.write_text("precious")
    (tmp_path / "out.h5.lock").symlink_to(victim)
    csv = _csv(tmp_path / "a.csv")
    before = tree(tmp_path)
    code, out, err = cli(["import", "-o", tmp_path / "out.h5", "--linear", csv], capsys)
    assert code == 2 and "out.h5.lock is a symbolic link; it is never followed" in one_line(err)
    assert tree(tmp_path) == before and victim.read_text() == "precious"
    os.unlink(tmp_path / "out.h5.lock")
    os.mkfifo(tmp_path / "out.h5.lock")          # not a regular file either
    with pytest.raises(UserFacingError, match="not a regular file"):
        OutputLock(tmp_path / "out.h5").acquire()


# ---- 3 and 6: Ctrl-C and SIGTERM while import or write-back writes --------------------------------------

SLOW_WRITES = """
import sys, time
from shakerlab.runfile import writer
append = writer.StageWriter.append
def slow(self, *a, **k):
    time.sleep(0.4)          # a large file's write, made slow enough to be interrupted in it
    return append(self, *a, **k)
writer.StageWriter.append = slow
import shakerlab.import_command as ic
ic.APPEND_BLOCK = 64
from shakerlab.cli import main
sys.exit(main(sys.argv[1:]))
"""


@pytest.mark.parametrize("sig, code, word", [(signal.SIGINT, 130, "interrupted (Ctrl-C)"),
                                             (signal.SIGTERM, 143, "terminated (SIGTERM)")])
def test_issue69_3_6_a_signal_stops_import_and_keeps_the_old_file(tmp_path, run_file, sig, code, word):
    out = tmp_path / "out.h5"
    out.write_bytes(run_file.read_bytes())
    csv = _csv(tmp_path / "a.csv", n=400)
    before = tree(tmp_path)
    proc = subprocess.Popen([sys.executable, "-c", SLOW_WRITES, "import", "--force", "-o", str(out), "--linear",
                             str(csv)], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=_env())
    deadline = time.monotonic() + 30
    while not (tmp_path / "out.h5.partial").exists() and time.monotonic() < deadline:
        time.sleep(0.01)
    assert (tmp_path / "out.h5.partial").exists()
    time.sleep(0.3)                                   # inside the writes
    proc.send_signal(sig)
    stdout, stderr = proc.communicate(timeout=30)
    assert proc.returncode == code, stderr
    assert word in one_line(stderr) and "Exception ignored" not in stderr
    assert tree(tmp_path) == before and leftovers(tmp_path) == []


SLOW_WRITE_BACK = """
import sys, time, shutil
from shakerlab.runfile import results
copy2 = shutil.copy2
def slow(a, b):
    print("copying", flush=True)
    time.sleep(1.0)          # a large run file's copy, made slow enough to be interrupted in it
    return copy2(a, b)
results.shutil.copy2 = slow
from shakerlab.cli import terminate_raises
terminate_raises()
try:
    results.add_result(sys.argv[1], "reconstruction", {"a": 1})
except KeyboardInterrupt as exc:
    sys.exit(143 if type(exc).__name__ == "Terminated" else 130)
"""


@pytest.mark.parametrize("sig, code", [(signal.SIGINT, 130), (signal.SIGTERM, 143)])
def test_issue69_3_6_a_signal_during_write_back_leaves_the_run_file(run_copy, tmp_path, sig, code):
    before = tree(tmp_path)
    proc = subprocess.Popen([sys.executable, "-c", SLOW_WRITE_BACK, str(run_copy)], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, env=_env())
    assert proc.stdout.readline().strip() == "copying"
    time.sleep(0.2)
    proc.send_signal(sig)
    _, stderr = proc.communicate(timeout=30)
    assert proc.returncode == code, stderr
    assert "Exception ignored" not in stderr
    assert tree(tmp_path) == before and leftovers(tmp_path) == [] and read_results(run_copy) == {}


def test_issue69_6_a_stale_import_partial_does_not_block_force(tmp_path, run_file, capsys):
    out = tmp_path / "out.h5"
    out.write_bytes(run_file.read_bytes())
    killed = subprocess.Popen([sys.executable, "-c", "import os, sys\nfrom shakerlab.runfile.writer import RunWriter\n"
                               "w = RunWriter(sys.argv[1], overwrite=True, attrs={'source': 'import'})\n"
                               "os.kill(os.getpid(), 9)", str(out)], env=_env())
    killed.wait(timeout=30)
    assert killed.returncode == -9 and (tmp_path / "out.h5.partial").exists()
    csv = _csv(tmp_path / "a.csv")
    before = {k: v for k, v in tree(tmp_path).items() if k not in ("out.h5", "out.h5.partial", "out.h5.lock")}
    code, stdout, err = cli(["import", "--force", "-o", out, "--linear", csv], capsys)
    assert code == 0, err
    assert f"removed {tmp_path / 'out.h5.partial'}, left by an import that was killed (pid {killed.pid}" in stdout
    assert read_info(out)["status"] == "complete" and leftovers(tmp_path) == []
    assert {k: v for k, v in tree(tmp_path).items() if k != "out.h5"} == before
    # a recording's partial file is never removed: it holds data nothing else has
    (tmp_path / "r.h5.partial").write_bytes(run_file.read_bytes())
    code, _, err = cli(["import", "--force", "-o", tmp_path / "r.h5", "--linear", csv], capsys)
    assert code == 2 and "interrupted recording" in one_line(err)
    assert (tmp_path / "r.h5.partial").read_bytes() == run_file.read_bytes()


# ---- 4: a full disk ------------------------------------------------------------------------------

@pytest.fixture
def small_fs(tmp_path):
    """A 2 MB tmpfs mounted for the test (needs root); skipped where mounting is not permitted."""
    mnt = tmp_path / "small"
    mnt.mkdir()
    if os.geteuid() != 0:
        pytest.skip("mounting a small tmpfs needs root; the full-disk paths are not exercised here")
    r = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=2m", "tmpfs", str(mnt)], capture_output=True, text=True)
    if r.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here ({r.stderr.strip()})")
    try:
        yield mnt
    finally:
        subprocess.run(["umount", "-l", str(mnt)], check=False)


def _fill(d, leave: int):
    """Fill the file system of ``d`` until ``leave`` bytes are free."""
    st = os.statvfs(d)
    free = st.f_bavail * st.f_frsize
    with open(d / "filler", "ab") as fh:
        try:
            fh.write(b"\0" * max(free - leave, 0))
        except OSError as exc:
            assert exc.errno == errno.ENOSPC


def test_issue69_4_full_disk_import_force_keeps_the_old_file(small_fs, run_file, tmp_path, capsys):
    old = small_fs / "out.h5"
    old.write_bytes(run_file.read_bytes()[:300_000] if run_file.stat().st_size > 300_000 else run_file.read_bytes())
    csv = _csv(tmp_path / "big.csv", n=60_000)         # about 2.5 MB in the run file: more than the disk holds
    _fill(small_fs, 200_000)
    before = tree(small_fs)
    code, _, err = cli(["import", "--force", "-o", old, "--linear", csv], capsys)
    assert code == 2
    line = one_line(err)
    assert f"no space left on {small_fs}" in line and "out.h5 was left as it was" in line
    assert tree(small_fs) == before and leftovers(small_fs) == []
    # with no byte free, taking the lock is the first write: the same one line
    _fill(small_fs, 0)
    before = tree(small_fs)
    code, _, err = cli(["import", "-o", small_fs / "new.h5", "--linear", _csv(tmp_path / "a.csv")], capsys)
    assert code == 2 and "no space left on" in one_line(err)
    with pytest.raises(UserFacingError, match=rf"no space left on {small_fs} \(writing {small_fs}/new.h5.lock\)"):
        OutputLock(small_fs / "new.h5").acquire()
    assert tree(small_fs) == before and leftovers(small_fs) == []


def test_issue69_4_full_disk_write_back_and_figures(small_fs, run_file, capsys):
    path = small_fs / "run.h5"
    path.write_bytes(run_file.read_bytes())
    _fill(small_fs, 50_000)
    before = tree(small_fs)
    with pytest.raises(UserFacingError, match=rf"no space left on {small_fs} .*run.h5 was left as it was"):
        add_result(path, "reconstruction", {"a": 1})
    group, note = store_result(path, "reconstruction", {"a": 1})
    assert group is None and note.startswith("not written back: no space left on")
    assert tree(small_fs) == before and leftovers(small_fs) == []
    # a figure (PIL / matplotlib writing a PNG) on the full disk: the same one line, no temporary file
    from workflows.figures import plt, savefig

    _fill(small_fs, 0)
    fig, ax = plt.subplots(figsize=(20, 20))
    ax.imshow(np.random.default_rng(0).random((800, 800)))
    before = tree(small_fs)
    with pytest.raises(UserFacingError, match=rf"no space left on {small_fs}"):
        savefig(fig, small_fs / "big.png", dpi=100)
    assert tree(small_fs) == before and leftovers(small_fs) == []


def test_issue69_4_full_disk_report_write_back_is_a_failure(small_fs, run_file, tmp_path):
    """`report` whose write-back meets a full disk: the report is written (its folder is on another
    file system), then one line naming the full disk, exit 2, the run file and its disk unchanged."""
    path = small_fs / "run.h5"
    path.write_bytes(run_file.read_bytes())
    _fill(small_fs, 20_000)
    before = tree(small_fs)
    out = tmp_path / "report"
    r = subprocess.run([sys.executable, "-m", "shakerlab.cli", "report", str(path), "-o", str(out), "--no-polish",
                        "--no-uncertainty", "--quiet"], capture_output=True, text=True, env=_env(), timeout=300)
    assert r.returncode == 2, r.stdout + r.stderr
    line = one_line(r.stderr)
    assert f"no space left on {small_fs}" in line and "the run file is unchanged" in line
    assert (out / "index.html").is_file()
    assert tree(small_fs) == before and leftovers(small_fs) == []


def test_issue69_4_full_disk_acquire_stops_safely_and_keeps_the_partial(small_fs, tmp_path, capsys):
    proto = tmp_path / "p.toml"
    proto.write_text(SMALL_PROTOCOL)
    out = small_fs / "run.h5"
    r = subprocess.run([sys.executable, "-m", "shakerlab.cli", "acquire", "--sim-speed", "0", "--protocol", str(proto),
                        "-o", str(out)], capture_output=True, text=True, env=_env(), timeout=120)
    assert r.returncode == 2, r.stdout + r.stderr
    line = one_line(r.stderr)
    assert f"no space left on {small_fs} (writing {out}.partial" in line
    assert f"`shakerlab import --recover {out}.partial -o {out}`" in line
    assert "amplifier muted (read back" in r.stdout and "Traceback" not in r.stdout
    assert sorted(tree(small_fs)) == ["run.h5.partial"]          # no lock, no temporary file: the partial kept
    code, stdout, err = cli(["import", "--recover", f"{out}.partial", "-o", tmp_path / "rec.h5"], capsys)
    assert code == 0, err
    assert read_run(tmp_path / "rec.h5").stage("linear").t.size > 0


# ---- 5: write-back through a symbolic link -------------------------------------------------------------

def test_issue69_5_write_back_through_a_symlink_goes_into_its_target(run_copy, tmp_path):
    link = tmp_path / "link.h5"
    link.symlink_to(run_copy.name)
    group, note = store_result(link, "reconstruction", {"a": 1})
    assert group == "reconstruction_000"
    assert note == f"written into the run file {run_copy} (the target of the link {link}) as entry/results/reconstruction_000"
    assert link.is_symlink() and os.readlink(link) == run_copy.name      # the link stays a link
    assert list(read_results(run_copy)) == ["reconstruction_000"]
    assert leftovers(tmp_path) == []


# ---- 7: a large CSV is read in bounded memory ----------------------------------------------------------

def test_issue69_7_csv_import_memory_is_at_most_twice_the_file(tmp_path):
    from shakerlab.import_command import import_csv

    from helpers import write_csv

    csv = tmp_path / "big.csv"
    write_csv(csv, 40_000)
    size = csv.stat().st_size
    tracemalloc.start()
    try:
        import_csv(tmp_path / "big.h5", {"linear": csv})
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak <= 2 * size, f"peak {peak} bytes for a {size}-byte file"
    assert read_info(tmp_path / "big.h5")["stages"]["linear"]["n_samples"] == 40_000


# ---- 8: an output name that is not UTF-8 ---------------------------------------------------------------

def test_issue69_8_output_name_not_utf8(tmp_path, capsys):
    csv = _csv(tmp_path / "a.csv")
    bad = os.fsdecode(bytes(tmp_path) + b"/\xff\xfe.h5")
    before = tree(tmp_path)
    code, _, err = cli(["import", "-o", bad, "--linear", csv], capsys)
    assert code == 2 and "the name is not valid UTF-8" in one_line(err)
    assert tree(tmp_path) == before and os.listdir(tmp_path) == ["a.csv"]


# ---- 9: 2-D datasets ---------------------------------------------------------------------------------

def test_issue69_9_two_dimensional_datasets_are_refused_at_load(run_copy, capsys):
    with h5py.File(run_copy, "a") as f:
        for name in f["entry/stages"]:
            g = f["entry/stages"][name]
            for key in list(g):
                if key != "steps":
                    data, attrs = g[key][:], dict(g[key].attrs)
                    del g[key]
                    g.create_dataset(key, data=data[:, None])
                    g[key].attrs.update(attrs)
    before = tree(run_copy.parent)
    t0 = time.monotonic()
    code, _, err = cli(["reconstruct", run_copy], capsys)
    assert code == 2 and time.monotonic() - t0 < 10
    assert "dataset /entry/stages/linear/time has shape (" in one_line(err) and ", 1)" in err
    assert tree(run_copy.parent) == before


# ---- 10: a killed acquisition is recovered ---------------------------------------------------------------

def _kill_acquire(tmp_path, moment: str, delay: float) -> Path:
    from test_closed_loop import rig_toml_1khz

    proto = tmp_path / "p.toml"
    proto.write_text(SMALL_PROTOCOL)
    out = tmp_path / "run.h5"
    # sampled at 1 kHz (the shipped rig config otherwise): a tenth of the samples to stream and write before
    # the moment of the kill; the recovery reads whatever the file holds at any rate
    rig = rig_toml_1khz(tmp_path)
    proc = subprocess.Popen([sys.executable, "-m", "shakerlab.cli", "acquire", "--config", str(rig), "--simulated",
                             "--sim-speed", "0", "--protocol", str(proto), "-o", str(out)], stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                            env=_env(), start_new_session=True)
    seen = []
    try:
        for line in proc.stdout:
            seen.append(line)
            if moment in line:
                time.sleep(delay)
                break
    finally:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()
    assert any(moment in s for s in seen), "".join(seen)
    return out


@pytest.mark.parametrize("moment, delay", [
    ("stage resonance_search begins", 0.05),     # mid-stage, early: the event log's last strings unflushed
    ("stage resonance_search begins", 0.4),      # mid-stage, later
    ("stage linear complete", 0.0),              # between stages
    ("nonlinear level 2", 0.0),                  # during a step change (the next level's ramp)
])
def test_issue69_10_a_killed_acquisition_is_recovered(tmp_path, moment, delay, capsys):
    out = _kill_acquire(tmp_path, moment, delay)
    partial = out.with_name("run.h5.partial")
    assert partial.exists() and not out.exists()
    readable = {}
    with h5py.File(partial, "r") as f:             # what h5py reads of the crashed file, stage by stage
        for name, g in f["entry/stages"].items():
            readable[name] = min(g[k].shape[0] for k in g if k not in ("steps", "control"))
    before = tree(tmp_path)
    code, stdout, err = cli(["import", "--recover", partial, "-o", tmp_path / "rec.h5"], capsys)
    assert code == 0, err
    assert "status recovered" in stdout
    after = tree(tmp_path)
    assert {k: v for k, v in after.items() if k != "rec.h5"} == before    # the partial file untouched
    info = read_info(tmp_path / "rec.h5")
    assert info["status"] == "recovered" and info["clean_close"]
    for name, n in readable.items():
        assert info["stages"][name]["n_samples"] == n                    # every readable sample kept
    run = read_run(tmp_path / "rec.h5")
    assert run.stage("linear").t.size == readable["linear"]
    with h5py.File(tmp_path / "rec.h5", "r") as f:
        notes = [m.decode() for m in f["entry/events"]["message"] if m.decode().startswith("recovery: ")]
    assert notes == [ln.removeprefix("recovery: ") and ln for ln in stdout.splitlines()
                     if ln.startswith("recovery: ")]


def test_issue69_10_a_dataset_hdf5_cannot_copy_is_rebuilt(tmp_path, capsys):
    """Steps (a compound with a variable-length label) written after the last flush: h5py's copy fails
    with "bad heap index"; recovery rebuilds it from its readable rows and says so."""
    crash = subprocess.run([sys.executable, "-c", """
import os, sys, numpy as np
from shakerlab.runfile.writer import RunWriter
w = RunWriter(sys.argv[1], flush_interval=1e9)
sw = w.begin_stage("linear", fs=100.0)
sw.append(0, {"x_base": np.zeros(500), "x_tip": np.ones(500)})
for i in range(3):
    sw.add_step(i, 0.1, 8.0, "flushed %d" % i)
w.flush()
for i in range(3, 40):
    sw.add_step(10 * i, 0.1, 8.0, "never flushed %d" % i)
    w.log("info", "event %d" % i)
os._exit(9)
""", str(tmp_path / "run.h5")], env=_env())
    assert crash.returncode == 9
    partial = tmp_path / "run.h5.partial"
    before = tree(tmp_path)
    code, stdout, err = cli(["import", "--recover", partial, "-o", tmp_path / "rec.h5"], capsys)
    assert code == 0, err
    assert "recovery: /entry/stages/linear/steps: damaged as stored (" in stdout and "bad heap index" in stdout
    assert "rebuilt from its 3 row(s), every row kept" in stdout
    assert {k: v for k, v in tree(tmp_path).items() if k != "rec.h5"} == before
    run = read_run(tmp_path / "rec.h5")
    assert run.attrs["status"] == "recovered" and run.stage("linear").t.size == 500
    assert [s["label"] for s in run.stage("linear").settings["steps"]] == ["flushed 0", "flushed 1", "flushed 2"]


# ---- also: sim serve beyond loopback ---------------------------------------------------------------------

def test_issue69_also_sim_serve_warns_beyond_loopback():
    for host, warned in (("0.0.0.0", True), ("127.0.0.1", False)):
        r = subprocess.run([sys.executable, "-m", "shakerlab.cli", "sim", "serve", "--host", host, "--duration", "0.2"],
                           capture_output=True, text=True, env=_env(), timeout=60)
        assert r.returncode == 0, r.stderr
        assert ("serves the simulated instruments beyond this machine" in r.stderr) == warned, r.stderr


# ---- property: stage names and output paths ------------------------------------------------------------

NAMES = st.text(alphabet=st.characters(blacklist_categories=("Cs",)), min_size=0, max_size=20) | st.sampled_from(
    ["..", ".", "../x", "a/../b", "a\\b", "/abs", "x\0y", "validation", "nonlinear_2", "a..b", ".hidden", "ü-1.2"])


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(name=NAMES)
def test_issue69_property_stage_names_never_leave_the_output_folder(tmp_path, name):
    try:
        check_stage_name(name, "run.npz")
    except UserFacingError as exc:
        assert "is not a plain name" in str(exc)
        accepted = False
    else:
        accepted = True
        assert "/" not in name and "\\" not in name and ".." not in name and name[:1] not in ("", ".", "-")
    if accepted:
        p = inside(tmp_path, name, ".png")
        assert p.resolve().parent == tmp_path.resolve()
    else:
        try:
            p = inside(tmp_path, name, ".png")
        except UserFacingError:
            return
        assert p.resolve().parent == tmp_path.resolve()       # a refused stage name may still be a safe file name

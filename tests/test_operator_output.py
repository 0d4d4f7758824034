"""What the operator sees: progress on stderr that never pauses, one verdict sentence, one
vocabulary (NRMSE, parameter names and units, output options), no escape codes, the HTML report
in a real browser."""
from __future__ import annotations

import json
import os
import pty
import re
import select
import shutil
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from recon.diagnosis.wording import diagnosis_text, finding_text
from recon.estimator.adequacy import verdict_summary
from recon.testing.truth import sdof_run
from shakerlab.cli import build_parser, main
from shakerlab.runfile.reader import save_npz
from shakerlab.words import fn_term_units, nrmse_text
from workflows.batch import format_table, write_simulated_run

ROOT = Path(__file__).resolve().parents[1]
MAX_SILENCE_S = 5.0


@pytest.fixture(scope="module")
def short_run(tmp_path_factory):
    """A 2 s run at 1 kHz: reconstruct takes seconds, diagnose tens of seconds."""
    path = tmp_path_factory.mktemp("operator") / "short.npz"
    run, _ = sdof_run("base", snr_db=80.0, seed=7, duration=2.0, fs=1000.0)
    save_npz(run, path)
    return path


def _env():
    return {**os.environ, "PYTHONPATH": str(ROOT), "PYTHONUNBUFFERED": "1"}


def _timed_stderr(args: list[str]) -> tuple[list[tuple[float, str]], str, int, float]:
    """Run ``shakerlab ARGS``; (time each stderr line arrived, the line), stdout, exit status, total seconds."""
    t0 = time.monotonic()
    proc = subprocess.Popen([sys.executable, "-m", "shakerlab.cli", *args], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, env=_env(), cwd=ROOT)
    out = []
    reader = threading.Thread(target=lambda: out.append(proc.stdout.read()))
    reader.start()
    lines = [(time.monotonic() - t0, line.rstrip("\n")) for line in proc.stderr]
    code = proc.wait(timeout=600)
    reader.join()
    return lines, out[0], code, time.monotonic() - t0


def _longest_silence(lines, total) -> float:
    times = [0.0] + [t for t, _ in lines] + [total]
    return max(b - a for a, b in zip(times, times[1:]))


@pytest.fixture(scope="module")
def quiet_reconstruct(short_run):
    """`reconstruct SHORT --no-polish --json --quiet`, run once for the module: (stderr lines, stdout,
    exit status). The progress test checks its silence, the verdict test reads its JSON."""
    lines, out, code, _ = _timed_stderr(["reconstruct", str(short_run), "--no-polish", "--json", "--quiet"])
    return lines, out, code


@pytest.mark.parametrize("command", [["reconstruct", "--no-polish"], ["diagnose", "--baseline", "linear"]])
def test_progress_never_silent_and_json_stays_clean(short_run, command, request):
    lines, out, code, total = _timed_stderr([command[0], str(short_run), *command[1:], "--json"])
    assert code == 0, lines
    d = json.loads(out)                      # stdout is one JSON object, nothing else
    assert isinstance(d, dict) and out.strip().count("\n") == 0
    gap = _longest_silence(lines, total)
    assert gap <= MAX_SILENCE_S, f"{gap:.1f} s without output on stderr:\n" + "\n".join(f"{t:6.1f} {x}" for t, x in lines)
    steps = [x for _, x in lines if x.startswith("[")]
    assert steps and all(re.match(r"\[ *\d+ %\] .+ \(.* elapsed", x) for x in steps), lines
    assert lines[-1][1].startswith("done in")
    if command[0] == "diagnose":
        assert any("candidate" in x for x in steps) and d["result_text"] == diagnosis_text(d)
    else:
        assert any("fitting the two stages together" in x or "revising" in x or "first estimate" in x for x in steps)
    quiet, out_q, code_q = request.getfixturevalue("quiet_reconstruct") if command[0] == "reconstruct" else ([], out, 0)
    assert code_q == 0 and quiet == [] and json.loads(out_q)


def test_reconstruct_verdict_one_sentence_everywhere_and_no_escape_codes(short_run, quiet_reconstruct):
    """The text line and the JSON key are the same sentence; on a terminal the output holds no escape code."""
    master, slave = pty.openpty()
    proc = subprocess.Popen([sys.executable, "-m", "shakerlab.cli", "reconstruct", str(short_run), "--no-polish"],
                            stdout=slave, stderr=slave, env=_env(), cwd=ROOT)
    os.close(slave)
    data = b""
    while True:
        ready, _, _ = select.select([master], [], [], 120)
        if not ready:
            break
        try:
            chunk = os.read(master, 65536)
        except OSError:
            break
        if not chunk:
            break
        data += chunk
    assert proc.wait(timeout=60) == 0
    text = data.decode()
    assert "\x1b" not in text, repr(text[-200:])
    verdicts = [x for x in text.replace("\r\n", "\n").split("\n") if x.startswith("verdict: ")]
    assert len(verdicts) == 1
    _, out, code = quiet_reconstruct
    assert code == 0
    d = json.loads(out)
    assert verdicts[0] == f"verdict: {d['verdict_text']}" == f"verdict: {verdict_summary(d['adequacy'])['text']}"
    assert "admissible" in d["verdict_text"] and "adequacy" in d and "verdict" in d["adequacy"]
    nrmse_line = next(x for x in text.splitlines() if x.startswith("validation NRMSE"))
    assert nrmse_line.rstrip().endswith(nrmse_text(d["validation"]["nrmse"]))


def test_verdict_never_contradicts_itself():
    fallback = {"verdict": "inadequate", "admissible": True, "validation_nrmse": 0.2, "nrmse_limit": 0.0106,
                "fn_terms": 2, "reasons": [], "fallback": {"used": True, "kind": "bouc_wen", "trigger": "inadmissible"}}
    v = verdict_summary(fallback)
    assert v["level"] == "bad" and v["text"].startswith("Fallback: the full model was not physically admissible")
    assert "the simpler bouc_wen model; it is admissible but inadequate" in v["text"]
    assert "20.0 %" in v["text"] and "1.06 %" in v["text"] and "shakerlab diagnose" in v["text"]
    good = dict(fallback, verdict="adequate", validation_nrmse=0.004, fallback={"used": False})
    g = verdict_summary(good)
    assert g["level"] == "good" and g["text"] == "The model is admissible and adequate (validation NRMSE 0.400 %, limit 1.06 %)."
    swapped = dict(good, fallback={"used": True, "kind": "bouc_wen_fewer_terms", "trigger": "inadequate"})
    s = verdict_summary(swapped)
    assert s["level"] == "warning" and "inadequate" not in s["text"].split(";")[-1]
    for a in (fallback, good, swapped):       # never both verdicts in one sentence about the answer
        t = verdict_summary(a)["text"]
        assert not ("is admissible and adequate" in t and "inadequate:" in t)


def test_one_vocabulary():
    assert [nrmse_text(v) for v in (0.000467095, 0.0039, 0.123456, None, float("inf"))] == \
        ["0.0467 %", "0.390 %", "12.3 %", "diverged", "diverged"]
    assert fn_term_units("y^2") == "1/(m*s^2)" and fn_term_units("y^3") == "1/(m^2*s^2)"
    assert fn_term_units("dy") == "1/s" and fn_term_units("y^2*dy") == "1/(m^2*s)" and fn_term_units("dy^2") == "1/m"
    rows = [{"run": "a.h5", "status": "ok", "nrmse": 0.000467, "parameters": {"k_m": 4000.0, "fn_m": {"y^3": 2e8}},
             "verdict": "adequate", "verdict_text": "The model is admissible and adequate (...).", "notes": []}]
    table = format_table(rows)
    head, row = table.splitlines()[:2]
    assert head.split() == ["run", "status", "nrmse", "verdict", "k_m", "fn_m[y^3]"]
    assert "0.0467 %" in row and "adequate" in row and "verdicts:" in table


def test_diagnosis_in_words():
    f = {"kind": "state_beyond_displacement", "stage": "nonlinear", "region": {"y_side": -1, "beyond_m": -0.000181},
         "size": 0.12}
    assert finding_text(f) == "stage 'nonlinear', beyond a displacement where y < -0.181 mm: size 12.0 %"
    assert "{" not in finding_text({"kind": "frequency_harmonic", "stage": "s", "region": {"frequency_hz": 28.4},
                                    "size": 0.01})
    nothing = {"missing_physics": [], "unexplained_mismatch": None, "mismatch": [f, f]}
    assert diagnosis_text(nothing).startswith("nothing found: the baseline predicts the held-out data within")
    assert "none of the 2 disagreement(s) located" in diagnosis_text(nothing)
    unexplained = dict(nothing, unexplained_mismatch={"held_out_nrmse": 0.05, "nrmse_limit": 0.01})
    assert diagnosis_text(unexplained).startswith("nothing in the catalog explains the mismatch: the held-out NRMSE 5.00 %")


def test_output_options_one_spelling_old_ones_deprecated(short_run, tmp_path, capsys):
    p = build_parser()
    for argv, dest in ((["reconstruct", "r.h5", "-o", "D"], "plots"), (["diagnose", "r.h5", "--output", "D"], "report")):
        assert getattr(p.parse_args(argv), dest) == "D"
    capsys.readouterr()
    a = p.parse_args(["reconstruct", "r.h5", "--plots", "D"])
    assert a.plots == "D" and "--plots is deprecated; use -o/--output" in capsys.readouterr().err
    a = p.parse_args(["diagnose", "r.h5", "--report", "D"])
    assert a.report == "D" and "--report is deprecated; use -o/--output" in capsys.readouterr().err
    assert p.parse_args(["reconstruct", "r.h5", "--uncertainty"]).uncertainty is True
    assert p.parse_args(["reconstruct", "r.h5", "--no-uncertainty"]).uncertainty is False
    for cmd in (["report", "r.h5", "-o", "D"], ["reprocess", "r.h5"]):
        assert p.parse_args(cmd).no_uncertainty is False
        assert p.parse_args(cmd + ["--no-uncertainty"]).no_uncertainty is True
        assert p.parse_args(cmd + ["--uncertainty"]).no_uncertainty is False
        assert p.parse_args(cmd + ["--form", "weak"]).form == "weak"
    assert p.parse_args(["sim", "serve", "--sim-speed", "max"]).speed == "max"
    assert p.parse_args(["acquire", "-o", "x.h5", "--sim-speed", "max"]).sim_speed == 0.0
    help_text = subprocess.run([sys.executable, "-m", "shakerlab.cli", "sim", "serve", "--help"], capture_output=True,
                               text=True, env=_env(), cwd=ROOT).stdout
    assert "Start the simulated rig's instruments" in help_text and "--sim-speed" in help_text
    # the old spelling still works end to end
    assert main(["reconstruct", str(short_run), "--no-polish", "--quiet", "--plots", str(tmp_path / "png")]) == 0
    assert len(list((tmp_path / "png").glob("*.png"))) == 2


def test_demo_refuses_an_existing_folder(tmp_path, capsys):
    out = tmp_path / "demo"
    out.mkdir()
    (out / "mine.txt").write_text("keep me")
    assert main(["demo", "-o", str(out)]) == 2
    err = capsys.readouterr().err
    assert "the folder exists and is not empty" in err and "--force" in err
    assert (out / "mine.txt").read_text() == "keep me"
    assert "/shakerlab-demo/" in (ROOT / ".gitignore").read_text().splitlines()


# --- the HTML report in a real browser --------------------------------------------------------------

CHROMIUM = next((shutil.which(n) for n in ("chromium", "chromium-browser", "google-chrome") if shutil.which(n)), None)
# a script the browser runs after load: what a reader sees, written into the page for --dump-dom
PROBE = """<script>window.addEventListener('load', function () {
  var imgs = Array.prototype.slice.call(document.images);
  var ok = imgs.filter(function (i) { return i.complete && i.naturalWidth > 0; }).length;
  var v = document.getElementById('verdict');
  var r = document.createElement('pre'); r.id = 'probe';
  r.textContent = JSON.stringify({images: imgs.length, loaded: ok,
    verdict: v ? v.innerText : null, verdictColour: v ? getComputedStyle(v).backgroundColor : null,
    verdictHeight: v ? v.getBoundingClientRect().height : 0});
  document.body.appendChild(r);
});</script>"""


@pytest.fixture(scope="module")
def report_dir(tmp_path_factory):
    d = tmp_path_factory.mktemp("html")
    write_simulated_run(d / "run.h5", fs=1000.0, duration=2.0, seed=1)
    assert main(["report", str(d / "run.h5"), "-o", str(d / "rep"), "--no-uncertainty", "--no-polish", "--quiet",
                 "--no-write-back"]) == 0
    return d / "rep"


def test_report_html_has_verdict_units_and_readable_timings(report_dir):
    html = (report_dir / "index.html").read_text()
    d = json.loads((report_dir / "result.json").read_text())
    assert "id='verdict'" in html and d["verdict_text"] in html.replace("&#x27;", "'").replace("&quot;", '"')
    assert "see fn_m units" not in html and "a[y^" not in html
    for term in d["parameters"]["fn_m"]:
        assert f"<td>fn_m[{term}]</td>" in html and f"<td>{fn_term_units(term)}</td>" in html
    timings = html.split("<h2>Timings</h2>")[1].split("</p>")[0]
    assert "{" not in timings and re.search(r"reconstruction \d", timings)


@pytest.mark.skipif(CHROMIUM is None, reason="no chromium binary (the CI script installs the distribution's package)")
def test_report_renders_in_headless_chromium(report_dir, tmp_path):
    page = tmp_path / "probe.html"
    page.write_text((report_dir / "index.html").read_text().replace("</body>", PROBE + "</body>"))
    flags = [CHROMIUM, "--headless", "--no-sandbox", "--disable-gpu", "--no-first-run",
             f"--user-data-dir={tmp_path / 'profile'}", "--virtual-time-budget=5000"]
    dom = subprocess.run(flags + ["--dump-dom", page.as_uri()], capture_output=True, text=True, timeout=120).stdout
    m = re.search(r"<pre id=\"probe\">(.*?)</pre>", dom, re.S)
    assert m, dom[-2000:]
    probe = json.loads(m.group(1).replace("&quot;", '"').replace("&amp;", "&"))
    figures = (report_dir / "index.html").read_text().count("src='data:image/png;base64,")
    assert probe["images"] == figures >= 5 and probe["loaded"] == figures
    assert probe["verdict"].startswith("Verdict: ") and probe["verdictHeight"] > 10
    assert probe["verdictColour"] in ("rgb(230, 244, 234)", "rgb(255, 244, 224)", "rgb(253, 232, 232)")
    shot = tmp_path / "report.png"
    subprocess.run(flags + ["--window-size=1200,1600", f"--screenshot={shot}", (report_dir / "index.html").as_uri()],
                   capture_output=True, timeout=120)
    assert shot.stat().st_size > 20_000
    if os.environ.get("SHAKERLAB_SAVE_SCREENSHOTS"):
        shutil.copy(shot, ROOT / "docs" / "screenshots" / "report.png")

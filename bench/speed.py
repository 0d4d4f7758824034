"""CPU time, peak memory and accuracy of `shakerlab reconstruct` and `shakerlab diagnose`.

Run:  .venv/bin/python bench/speed.py [--jobs reconstruct diagnose] [--cases c01 c02 c03 demo]
                                      [--no-sindy] [--work DIR] [--repeat N]

Each job runs as its own `shakerlab` process (as a user runs it); the table gives the CPU seconds
(user + system) and the peak resident memory of that whole process, read from the operating system
(os.wait4), and the validation NRMSE it printed. Cases: the shared development set's c01-c03
(../shared/data/foreign_sdof, an independent simulator: three stages of 10-15 s at 1 kHz) and the
demo run (`shakerlab acquire` on the simulated rig, made once in --work). Beside them, PySINDy's
fit on c01 (the `bench` extra; STLSQ on the nonlinear stage, the threshold scanned), for scale.

The targets this table is read against: reconstruct <= 2 CPU-s on c01 and <= 5 on c02 and the
demo run; diagnose <= 10 CPU-s on c01 and <= 25 on c02; peak memory <= 250 MiB.
"""
from __future__ import annotations

import argparse
import gzip
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
DATA = REPO.parent / "shared" / "data" / "foreign_sdof"
STAGES = ("linear", "nonlinear", "validation")
SHAKERLAB = [sys.executable, "-m", "shakerlab.cli"]


# the jobs run as an installed shakerlab runs: with Python's bytecode cache. Under
# PYTHONDONTWRITEBYTECODE (set in some shells and containers) every process compiles the project's
# sources again, about 0.3 CPU-s a run that no user's install pays
CHILD_ENV = {k: v for k, v in os.environ.items() if k != "PYTHONDONTWRITEBYTECODE"}


def measured(cmd: list[str]) -> tuple[int, str, str, float, float, float]:
    """Run `cmd`; return (exit code, stdout, stderr, CPU seconds, peak MiB, wall seconds)."""
    with tempfile.TemporaryFile() as out, tempfile.TemporaryFile() as err:
        t0 = time.perf_counter()
        p = subprocess.Popen(cmd, stdout=out, stderr=err, stdin=subprocess.DEVNULL, env=CHILD_ENV)
        _, status, ru = os.wait4(p.pid, 0)
        wall = time.perf_counter() - t0
        p.returncode = os.waitstatus_to_exitcode(status)
        out.seek(0)
        err.seek(0)
        cpu = ru.ru_utime + ru.ru_stime
        return p.returncode, out.read().decode(), err.read().decode(), cpu, ru.ru_maxrss / 1024, wall


def run_file(case: str, work: Path) -> Path:
    h5 = work / f"{case}.h5"
    if h5.exists():
        return h5
    if case == "demo":
        rc, out, err, *_ = measured(SHAKERLAB + ["acquire", "-o", str(h5), "--sim-speed", "0"])
        if rc != 0:
            raise SystemExit(f"acquire for the demo run failed ({rc}): {err.strip()[-400:]}")
        return h5
    args = SHAKERLAB + ["import", "-o", str(h5)]
    for st in STAGES:
        csv = work / f"{case}_{st}.csv"
        with gzip.open(DATA / f"{case}_{st}.csv.gz", "rb") as fi, open(csv, "wb") as fo:
            shutil.copyfileobj(fi, fo)
        args += [f"--{st}", str(csv)]
    rc, out, err, *_ = measured(args)
    if rc != 0:
        raise SystemExit(f"import of {case} failed ({rc}): {err.strip()[-400:]}")
    return h5


def last_json(text: str) -> dict:
    start = text.find("{")
    while start != -1:
        try:
            return json.loads(text[start:])
        except json.JSONDecodeError:
            start = text.find("{", start + 1)
    return {}


def job(kind: str, h5: Path) -> dict:
    cmd = SHAKERLAB + [kind, str(h5), "--json"]
    rc, out, err, cpu, mib, wall = measured(cmd)
    r = last_json(out) if rc == 0 else {}
    if kind == "reconstruct":
        nr = (r.get("validation") or {}).get("nrmse")
        answer = ", ".join(sorted((r.get("parameters") or {}).get("fn_m", {}) or {})) or "-"
    else:
        after = (r.get("fit_after") or {}).get("nrmse") or {}
        nr = after.get("validation") if isinstance(after, dict) else None
        named = [c.get("id") for c in r.get("missing_physics", [])]
        answer = ", ".join(named) or "nothing"
    return {"rc": rc, "cpu": cpu, "mib": mib, "wall": wall, "nrmse": nr, "answer": answer,
            "error": err.strip().splitlines()[-1] if rc and err.strip() else ""}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--jobs", nargs="+", default=["reconstruct", "diagnose"], choices=("reconstruct", "diagnose"))
    ap.add_argument("--cases", nargs="+", default=["c01", "c02", "c03", "demo"])
    ap.add_argument("--work", type=Path, help="folder for the imported run files (default: a new temporary one)")
    ap.add_argument("--repeat", type=int, default=1, help="runs per job; the table gives the median CPU")
    ap.add_argument("--no-sindy", action="store_true", help="skip PySINDy's fit on c01")
    args = ap.parse_args()
    if any(c != "demo" for c in args.cases) and not DATA.is_dir():
        raise SystemExit(f"the development set is not beside this checkout: {DATA}")
    work = args.work or Path(tempfile.mkdtemp(prefix="shakerlab-speed-"))
    work.mkdir(parents=True, exist_ok=True)
    # the bytecode cache written once, as an install's first command writes it (CHILD_ENV)
    measured([sys.executable, "-c", "import shakerlab.cli, workflows.handlers, recon.diagnosis.diagnose"])
    print(f"{'job':12s} {'case':5s} {'CPU s':>7s} {'wall s':>7s} {'peak MiB':>9s} {'val. NRMSE':>11s}  answer")
    for kind in args.jobs:
        for case in args.cases:
            h5 = run_file(case, work)
            rows = sorted((job(kind, h5) for _ in range(args.repeat)), key=lambda r: r["cpu"])
            r = rows[len(rows) // 2]
            nr = f"{r['nrmse']:.3g}" if isinstance(r["nrmse"], (int, float)) else "-"
            note = r["answer"] if r["rc"] == 0 else f"exit {r['rc']}: {r['error'][:60]}"
            print(f"{kind:12s} {case:5s} {r['cpu']:7.1f} {r['wall']:7.1f} {r['mib']:9.0f} {nr:>11s}  {note}",
                  flush=True)
    if not args.no_sindy and "c01" in args.cases:
        s = sindy(work)
        if s:
            print(f"{'pysindy':12s} {'c01':5s} {s['cpu']:7.2f} {'':>7s} {'':>9s} {s['nrmse']:11.3g}  "
                  f"STLSQ threshold {s['threshold']:.3g}, {s['terms']} terms, no hysteretic state")
        else:
            print("pysindy: not installed (pip install -e '.[bench]')")
    return 0


def sindy(work: Path) -> dict | None:
    """PySINDy on c01: STLSQ with a polynomial library in (y, y') and u as control, fitted on the
    nonlinear stage with shakerlab's own Savitzky-Golay derivatives; the best of a threshold scan,
    simulated on the validation stage with the same RK4 scheme (bench/recon_speed.py)."""
    try:
        import numpy as np
        import pysindy as ps
    except ImportError:
        return None
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from recon_speed import simulate_polynomial
    from shakerlab.runfile.reader import load_run
    from recon.signals import stage_signals
    from recon.validation import nrmse
    from recon import reconstruct, ReconSettings

    run = load_run(run_file("c01", work))
    st = run.stage("nonlinear")
    t0 = time.process_time()
    sig = stage_signals(st, 3)
    x = np.column_stack([sig.y[0], sig.y[1]])
    xdot = np.column_stack([sig.y[1], sig.y[2]])
    u = sig.u[0][:, None]
    best = None
    for thr in np.geomspace(1e-4, 1.0, 9):
        mdl = ps.SINDy(optimizer=ps.STLSQ(threshold=float(thr), normalize_columns=True),
                       feature_library=ps.PolynomialLibrary(degree=5))
        mdl.fit(x, t=st.dt, x_dot=xdot, u=u)
        r2 = mdl.score(x, t=st.dt, x_dot=xdot, u=u)
        if best is None or r2 > best[0]:
            best = (r2, float(thr), mdl)
    cpu = (time.process_time() - t0) / 9
    _, thr, mdl = best
    vst = run.stage("validation")
    uv = reconstruct(run, ReconSettings(polish=False)).model.stage_input(vst)
    ys = simulate_polynomial(mdl.coefficients(), np.asarray(mdl.feature_library.powers_, np.int64), uv, vst.dt)
    return {"cpu": cpu, "nrmse": float(nrmse(ys, vst.y)), "threshold": thr,
            "terms": int(np.count_nonzero(mdl.coefficients()[1]))}


if __name__ == "__main__":
    sys.exit(main())

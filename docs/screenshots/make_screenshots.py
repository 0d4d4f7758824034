"""Render the operator window offscreen during a run, after it and with a diagnosis; write the PNGs
shown in README.md and docs/gui.md.

    QT_QPA_PLATFORM=offscreen .venv/bin/python docs/screenshots/make_screenshots.py [--speed 1] [--out docs/screenshots]

Runs the shipped protocol (rig/default_protocol.toml) on the simulated rig at ``--speed`` times real
time through the window (same code path as ``shakerlab gui``), grabs the Run tab during the nonlinear
stage, waits for the end of the run and the reconstruction, and grabs the Results tab (with its
verdict banner). Then it writes a short synthetic record with Coulomb friction that its baseline
model leaves out (recon.testing.concealed, imported as a run file), opens it, presses *Diagnose*
and grabs the Diagnosis tab.
"""
from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--speed", type=float, default=1.0, help="simulated time per wall time (default 1: real time)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", type=Path, default=Path(__file__).resolve().parent)
    ap.add_argument("--timeout", type=float, default=600.0, help="give up after this many seconds")
    args = ap.parse_args(argv)
    os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")
    from PySide6 import QtWidgets

    app = QtWidgets.QApplication.instance() or QtWidgets.QApplication(["shakerlab"])
    from rig.gui.window import MainWindow

    workdir = Path(tempfile.mkdtemp(prefix="shakerlab-shots-"))
    w = MainWindow(output_dir=workdir, speed=args.speed, seed=args.seed)
    w.resize(1400, 900)
    w.show()
    deadline = time.monotonic() + args.timeout

    def spin_until(cond, what):
        while not cond():
            if time.monotonic() > deadline:
                w.shutdown()
                raise SystemExit(f"timed out waiting for {what}")
            app.processEvents()
            time.sleep(0.005)

    if not w.start_run():
        raise SystemExit(f"the run did not start: {w.last_error}")
    # the nonlinear stage, a few levels up, settled at a level (the live loop is drawn from steady windows)
    spin_until(lambda: w.live.stage == "nonlinear" and w.live.drive.amplitude_vpp >= 0.3
               and w.live.live_loop() is not None, "a steady level of the nonlinear stage")
    frames = w.frames
    spin_until(lambda: w.frames >= frames + 3, "a redraw")
    args.out.mkdir(parents=True, exist_ok=True)
    during = args.out / "gui-during-run.png"
    w.grab().save(str(during))
    print(f"wrote {during} (stage {w.live.stage}, {w.live.drive.amplitude_vpp:.3f} Vpp)")
    spin_until(lambda: w.last_outcome is not None, "the end of the run")
    if w.last_outcome.status != "complete":
        raise SystemExit(f"run {w.last_outcome.status}: {w.last_outcome.reason}")
    spin_until(lambda: w.last_view is not None or (w.last_error and "reconstruct" not in w.last_error), "the result")
    if w.last_view is None:
        raise SystemExit(f"no result: {w.last_error}")
    for _ in range(20):
        app.processEvents()
        time.sleep(0.02)
    after = args.out / "gui-after-run.png"
    w.grab().save(str(after))
    print(f"wrote {after} ({w.last_view.origin}; NRMSE {w.last_view.nrmse:.4f} on {w.last_view.validation_stage})")

    path, baseline = friction_record(workdir)
    w.last_view = None
    w.open_run(path)
    spin_until(lambda: w.last_view is not None or bool(w.last_error), "the friction record's result")
    if not w.diagnose_run(baseline=str(baseline)):
        raise SystemExit(f"the diagnosis did not start: {w.last_error}")
    spin_until(lambda: w.diagnosis_state != "running", "the diagnosis")
    if w.diagnosis_state != "done":
        raise SystemExit(f"diagnosis {w.diagnosis_state}: {w.last_error}")
    for _ in range(20):
        app.processEvents()
        time.sleep(0.02)
    diag = args.out / "gui-diagnosis.png"
    w.grab().save(str(diag))
    print(f"wrote {diag} ({w.last_diagnosis.sentence()})")
    w.close()
    return 0


def friction_record(workdir: Path):
    """A 3-stage synthetic record (1 s each) with Coulomb friction, as a run file, and its baseline
    model (the same structure without the friction) as a model JSON."""
    import numpy as np

    from recon.testing.concealed import concealed_run
    from shakerlab.import_command import import_csv
    from shakerlab.runfile.results import add_result

    run, _, _, baseline = concealed_run("coulomb_friction", duration=1.0, seed=2)
    files = {}
    for name, st in run.stages.items():
        csv = workdir / f"friction-{name}.csv"
        np.savetxt(csv, np.column_stack([st.t] + [st.channels[c] for c in st.channels]), delimiter=",",
                   header=",".join(["t", *st.channels]), comments="")
        files[name] = csv
    path = import_csv(workdir / "friction.h5", files)
    add_result(path, "reconstruction", {**baseline.to_dict(), "validation": {"stage": "validation"}},
               text=str(baseline))
    model = workdir / "baseline.json"
    baseline.save(model)
    return path, model


if __name__ == "__main__":
    sys.exit(main())

"""The operator GUI (``shakerlab gui``): PySide6 + pyqtgraph front end of the rig runner.

- :mod:`rig.gui.window`: the main window and its worker threads (run, reconstruction);
- :mod:`rig.gui.panels`: connection, protocol, live plots and results panels;
- :mod:`rig.gui.live_state`: the runner observer feeding the live plots (no Qt);
- :mod:`rig.gui.results`: the after-run view of a run file (no Qt).

See docs/gui.md.
"""
from __future__ import annotations

import signal
import threading


def run_gui(args) -> int:
    """Handler of ``shakerlab gui``: open the window, run the Qt event loop, stop safely."""
    import os  # heavy: Qt and pyqtgraph; loaded when the window opens
    import sys  # heavy: Qt and pyqtgraph; loaded when the window opens

    from rig.gui.startup import problem  # heavy: Qt and pyqtgraph; loaded when the window opens
    from shakerlab.errors import UserFacingError  # heavy: Qt and pyqtgraph; loaded when the window opens

    missing = problem()
    if missing is not None:
        raise UserFacingError(missing)

    from PySide6 import QtWidgets  # heavy: Qt and pyqtgraph; loaded when the window opens

    from rig.gui.window import MainWindow  # heavy: Qt and pyqtgraph; loaded when the window opens

    if not os.environ.get("DISPLAY") and not os.environ.get("WAYLAND_DISPLAY") and sys.platform.startswith("linux") \
            and not os.environ.get("QT_QPA_PLATFORM"):
        raise UserFacingError("no display (DISPLAY and WAYLAND_DISPLAY are unset); set QT_QPA_PLATFORM=offscreen "
                              "to run the window without one")
    app = QtWidgets.QApplication.instance() or QtWidgets.QApplication(["shakerlab"])
    simulated = None
    if args.simulated:
        simulated = True
    window = MainWindow(config_path=args.config, protocol_path=args.protocol, output_dir=args.output_dir,
                        simulated=simulated, speed=args.sim_speed, seed=args.seed)
    if args.open is not None:
        window.open_run(args.open)
    window.resize(1400, 900)
    window.show()
    app.aboutToQuit.connect(window.shutdown)
    if args.start and not window.start_run():
        print(f"shakerlab gui: the run did not start: {window.last_error}", file=sys.stderr)
    previous = _close_on_signals(window)
    try:
        return int(app.exec())
    finally:
        window.shutdown()
        for sig, old in previous.items():
            signal.signal(sig, old)


def _close_on_signals(window) -> dict:
    """Ctrl-C / SIGTERM close the window like its close button (a run is aborted safely first);
    a second one during that ramp-down cuts at once. The window's redraw timer lets Python run the
    handler within a frame."""
    from PySide6 import QtCore  # heavy: Qt and pyqtgraph; loaded when the window opens

    def handler(signum, frame):  # noqa: ARG001 - signal handler signature
        if window.running() and window._close_pending:
            QtCore.QTimer.singleShot(0, window.abort)
        else:
            QtCore.QTimer.singleShot(0, window.close)

    if threading.current_thread() is not threading.main_thread():
        return {}
    return {sig: signal.signal(sig, handler) for sig in (signal.SIGINT, signal.SIGTERM)}


def register_gui(subparsers) -> None:
    """Add ``shakerlab gui`` (called from rig/commands.py; import-light)."""
    from pathlib import Path  # heavy: Qt and pyqtgraph; loaded when the window opens

    from shakerlab.options import output_option  # lazy: the parser only, when commands are registered

    g = subparsers.add_parser(
        "gui",
        help="the operator window: run the protocol, watch it live, see the reconstructed equation",
        description="Open the operator window (PySide6 + pyqtgraph). It drives the same protocol runner as "
        "`shakerlab acquire`, on a simulated rig started here (default without --config) or on the instruments "
        "of --config; live plots come from in-memory buffers; after a complete run the governing equation is "
        "reconstructed off the GUI thread. ABORT ramps the output to zero, a second press cuts at once; closing "
        "the window mid-run (or Ctrl-C / SIGTERM) aborts the same way. Needs a display (or QT_QPA_PLATFORM=offscreen).",
    )
    g.add_argument("--config", type=Path, metavar="RIG.toml",
                   help="rig config (addresses, limits); given: the real instruments at its addresses")
    g.add_argument("--simulated", action="store_true",
                   help="with --config: use its limits on a simulated rig instead of its addresses")
    g.add_argument("--protocol", type=Path, metavar="PROTOCOL.toml",
                   help="protocol loaded into the editor (default: rig/default_protocol.toml)")
    output_option(g, "--output-dir", "run files are written here as run-YYYYmmdd-HHMMSS.h5 (default ./shakerlab-runs)",
                  type=Path, default=Path("shakerlab-runs"))
    g.add_argument("--sim-speed", type=float, default=1.0, metavar="X",
                   help="simulated time per wall time (1 = real time, 0 = as fast as possible)")
    g.add_argument("--seed", type=int, default=0, help="the simulated rig's noise seed")
    g.add_argument("--open", type=Path, metavar="RUN.h5", help="open a recorded run file and show its result")
    g.add_argument("--start", action="store_true", help="start the protocol at once (as if Start were pressed)")
    g.set_defaults(handler=run_gui)

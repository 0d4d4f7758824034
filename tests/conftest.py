import os
import sys
import time as _time

import pytest

# The tests run with Python's bytecode cache, as an installed shakerlab runs: under
# PYTHONDONTWRITEBYTECODE (set in some shells and containers) every worker and every `shakerlab`
# subprocess compiled the project's sources and rewrote the test files' assertions again (about
# 3 CPU-s of collection per worker, 0.3 s per subprocess). Cleared here, before pytest-xdist starts
# its workers, so they and the subprocesses inherit it.
os.environ.pop("PYTHONDONTWRITEBYTECODE", None)
sys.dont_write_bytecode = False

# Every test runs headless.
os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")
os.environ.setdefault("MPLBACKEND", "Agg")

# Under pytest-xdist every core already runs a worker process: the fits' finite differences stay
# on one thread there (recon/threads.py), as more threads than cores only slow each test down
# (a 141 s test took over 300 s with two workers of two threads each beside other load)
if os.environ.get("PYTEST_XDIST_WORKER"):
    os.environ.setdefault("SHAKERLAB_THREADS", "1")


# Scheduling (pyproject: --dist loadfile --no-loadscope-reorder): each file runs on one worker, so
# its module-scoped fixtures (a reconstruction or diagnosis shared by several tests) are computed
# once, not once per worker; the files below go first, heaviest first (the seconds of both tiers
# together, from a `--durations` run of each on 2 cores: a file heavy in the acceptance tier starts
# first there, and the fast tier's heavy files still start before its many small ones), so the last
# files to start are quick ones and the workers finish together. The order changes when a test
# runs, never what it checks; a file not listed keeps its place after these.
# test_gui.py goes second: in a fresh clone (numba's cache empty) the first two files start together,
# and the operator window's tests compile the simulated rig's kernels while the diagnosis's compile
# recon's, where two diagnosis files would compile the same kernels twice at once.
HEAVY_FIRST = (
    "test_diagnosis_honest.py", "test_gui.py", "test_diagnosis_harmonic.py", "test_diagnosis.py",
    "test_diagnosis_corner.py", "test_recon_fallback.py", "test_closed_loop.py", "test_determinism.py",
    "test_diagnosis_rig.py", "test_diagnosis_friction_words.py", "test_independent_generator.py",
    "test_data_safety.py",
    "test_diagnosis_velocity.py", "test_rig_end_to_end.py", "test_quantities.py", "test_rig_velocity.py",
    "test_recon_adversarial.py", "test_recon_input_offset.py", "test_acceleration_drift.py",
    "test_constitutive.py", "test_batch.py", "test_data_safety_faults.py", "test_recon_two_stage.py",
    "test_boucwen_single_level.py", "test_diagnosis_sensitivity.py", "test_rig_acquisition.py",
    "test_recon_mdof.py", "test_recon_simpler_fit_slack.py", "test_diagnosis_hardening_loop.py",
    "test_operator_output.py", "test_rig_cli.py", "test_report.py", "test_recon_exciter.py",
    "test_recon_elastic_start.py", "test_recon_weak_path.py", "test_recon_core.py", "test_recon_input_band.py",
    "test_sine_control.py", "test_layers.py", "test_weak_linear_stage.py",
)


def pytest_collection_modifyitems(session, config, items):
    rank = {name: i for i, name in enumerate(HEAVY_FIRST)}
    items.sort(key=lambda item: rank.get(item.path.name, len(rank)))     # stable: a file's own order is kept


# pyserial's socket:// transport (serial.urlhandler.protocol_socket, 3.5) sleeps 0.3 s in every
# close(), "in case of quick reconnects, give the server some time": a test that opens the three
# line instruments of a simulated rig spends 0.9 s of wall time closing them, idle (about 100
# tests did; issue 70). The simulated instruments (sim_backend.line_server) accept any number of
# connections at once, so the tests leave that pause out; the drivers and the rig are unchanged and
# still pause on a real rig. Only that module's time.sleep is replaced (its only sleep); a CLI
# run in a subprocess keeps the pause.
class _TimeWithoutSleep:
    def __getattr__(self, name):
        return getattr(_time, name)

    @staticmethod
    def sleep(seconds):
        pass


@pytest.fixture(autouse=True, scope="session")
def _no_pause_in_pyserial_socket_close():
    from serial.urlhandler import protocol_socket
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(protocol_socket, "time", _TimeWithoutSleep())
        yield

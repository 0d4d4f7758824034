"""One acquisition, start to end: instruments + supervisor + runner + recorder.

:func:`acquire` is what ``shakerlab acquire``, ``shakerlab demo``, the tests
and (later) the GUI call. :func:`simulated_rig` starts the embedded simulated
rig and returns the rig configuration pointing at it.
"""
from __future__ import annotations

import contextlib
from pathlib import Path

from rig.config import RigConfig, load_config
from rig.instruments import RigInstruments
from rig.plans import PlanContext, protocol_plan
from rig.protocol import Protocol
from rig.recorder import Recorder
from rig.runner import RunOutcome, Runner
from rig.safety import Supervisor
from shakerlab.errors import UserFacingError

# exit status of `shakerlab acquire` and `shakerlab demo` per run outcome
EXIT_CODES = {"complete": 0, "error": 1, "tripped": 3, "aborted": 130}


def acquire(config: RigConfig, protocol: Protocol, output: str | Path, *, lockstep: bool = False,
            observers=(), overwrite: bool = False, attrs: dict | None = None, texts: dict | None = None,
            on_runner=None, plan=None, append: bool = False) -> RunOutcome:
    """Run ``protocol`` on the rig at ``config``'s addresses and record to ``output``.

    ``append``: add the stages to the cleanly closed run file ``output`` (its configuration texts
    and attributes stay; ``texts`` and ``attrs`` are added), their sample indices continuing from its
    last sample (:class:`rig.recorder.Recorder`); the file is replaced by the extended one only when
    that is whole (:class:`shakerlab.runfile.writer.RunWriter`).

    ``on_runner(runner)`` is called before the run starts (to keep a handle
    for abort/pause, e.g. from a signal handler or a GUI button). ``plan``
    replaces the protocol's plan (tests). Instrument connection errors are
    raised before anything moves and before the file is created.
    """
    protocol.check_against_limits(config.limits, config.source)
    inst = RigInstruments(config, lockstep=lockstep)
    try:
        inst.connect()
    except Exception as exc:  # noqa: BLE001 - an unreachable instrument is a config problem for the user
        inst.close()
        raise UserFacingError(f"{config.source}: cannot reach the instruments ({type(exc).__name__}: {exc}); "
                              f"check the addresses and that the instruments are on") from None
    try:
        check_device_settings(config, inst)
        recorder = Recorder(output, overwrite=overwrite, flush_interval=config.acquisition["flush_interval_s"],
                            fs=inst.fs, quantities=inst.quantities, append=append)
    except Exception:
        inst.close()
        raise
    supervisor = Supervisor(config.limits)
    runner = Runner(inst, supervisor, observers=[recorder, *observers])
    if on_runner is not None:
        on_runner(runner)
    ctx = PlanContext(config.limits)
    info = {"rig_toml": config.text, "protocol_toml": protocol.text, **(texts or {}),
            "attrs": {"rig_config": config.source, "protocol": protocol.source, **(attrs or {})}}
    if append:      # the file keeps the texts and attributes of its first recording
        info = {**(texts or {}), "attrs": dict(attrs or {})}
    try:
        outcome = runner.run(plan if plan is not None else protocol_plan(protocol, config.limits, ctx), info)
    finally:
        inst.close()
    outcome.path = Path(output)
    outcome.context = ctx
    outcome.file_note = check_recording(recorder, outcome)
    return outcome


def check_device_settings(config: RigConfig, inst: RigInstruments) -> None:
    """The settings the instruments themselves bound, read from the connected devices: refused before
    the run file is created and before anything is driven."""
    amp = config.data["amplifier"]
    if inst.amp_kind != "shakerlab":
        return  # a declared map's gain_max is checked with the config; a manual amplifier reports nothing
    with inst.amp_lock:
        max_gain, max_current = inst.amp.max_gain, inst.amp.max_current_limit
    if amp["gain"] > max_gain:
        raise UserFacingError(f"{config.source}: [amplifier] gain: {amp['gain']:g} exceeds the amplifier's own "
                              f"maximum {max_gain:g} (read from the device); nothing was driven, no file written")
    if amp["current_limit_a"] > max_current:
        raise UserFacingError(f"{config.source}: [amplifier] current_limit_a: {amp['current_limit_a']:g} A exceeds "
                              f"the amplifier's own maximum {max_current:g} A (read from the device); nothing was "
                              f"driven, no file written")


def check_recording(recorder: Recorder, outcome: RunOutcome) -> str:
    """After the run: was the file closed, read back whole and renamed into place? Returns a note for
    the summary and turns a complete run whose file failed the check into an error."""
    w = recorder.writer
    if recorder.no_space is not None:
        outcome.path = w.partial
        outcome.status = "error"
        outcome.no_space = (f"{recorder.no_space}; the recording stopped, the output was ramped down, and the data "
                            f"recorded so far is in {w.partial}: `shakerlab import --recover {w.partial} -o "
                            f"{w.path}` on a disk with room makes the run file")
        return f"the disk filled up: the recorded data is in {w.partial} (recover it with `shakerlab import --recover`)"
    if recorder.discarded:
        outcome.path = None
        return (f"nothing recorded: {w.path} was left as it was" if w.path.exists()
                else "nothing recorded, no file written")
    if w.file.id.valid:      # on_run_end did not close it (an observer error while stopping)
        try:
            w.close(outcome.status)
        except Exception as exc:  # noqa: BLE001 - reported below; the data stays in the partial file
            w.problems.append(f"cannot be closed ({type(exc).__name__}: {exc})")
    if w.renamed and not w.problems:
        return f"checked: {w.n_recorded()} samples per channel read back from {w.path}"
    outcome.path = w.partial
    problem = "; ".join(w.problems) or "not renamed into place"
    if outcome.status == "complete":
        outcome.status = "error"
        outcome.reason = f"the run file failed its check after closing: {problem}"
    return (f"the run file failed its check ({problem}); the recorded data is in {w.partial} "
            f"(`shakerlab import --recover {w.partial} -o {w.path}`)")


@contextlib.contextmanager
def simulated_rig(speed: float | None = 1.0, seed: int = 0, sim_config=None,
                  rig_config: str | Path | RigConfig | None = None):
    """Start the simulated rig; yield (SimulatedRig, RigConfig with its addresses). With a manual amplifier
    the simulated amplifier's front panel is set to the config's gain, as the operator would."""
    from sim_backend.rig import SimulatedRig  # lazy: the simulator only when a simulated rig is asked for

    sim = SimulatedRig(sim_config, speed=speed, seed=seed)
    sim.start()
    try:
        config = rig_config if isinstance(rig_config, RigConfig) else load_config(rig_config)
        if config.amplifier_kind == "manual":
            # the operator's part: gain knob and output switch on the (simulated) front panel
            sim.amplifier.front_panel(config.data["amplifier"]["gain"])
        yield sim, config.with_addresses(sim.addresses)
    finally:
        sim.stop()

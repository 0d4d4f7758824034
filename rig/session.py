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
            on_runner=None, plan=None) -> RunOutcome:
    """Run ``protocol`` on the rig at ``config``'s addresses and record to ``output``.

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
        recorder = Recorder(output, overwrite=overwrite, flush_interval=config.acquisition["flush_interval_s"],
                            fs=inst.fs)
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
    try:
        outcome = runner.run(plan if plan is not None else protocol_plan(protocol, config.limits, ctx), info)
    finally:
        inst.close()
    outcome.path = Path(output)
    outcome.context = ctx
    return outcome


@contextlib.contextmanager
def simulated_rig(speed: float | None = 1.0, seed: int = 0, sim_config=None, rig_config: str | Path | None = None):
    """Start the simulated rig; yield (SimulatedRig, RigConfig with its addresses)."""
    from sim_backend.rig import SimulatedRig  # lazy: the simulator only when a simulated rig is asked for

    sim = SimulatedRig(sim_config, speed=speed, seed=seed)
    sim.start()
    try:
        yield sim, load_config(rig_config).with_addresses(sim.addresses)
    finally:
        sim.stop()

"""Sub-commands contributed by ``rig``: ``acquire`` and ``gui`` (see shakerlab.cli).

Kept import-light: the handlers import the heavy modules.
"""
from __future__ import annotations

import math
from pathlib import Path

from rig.gui import register_gui  # the operator window (rig/gui/); import-light



def sim_speed(text: str) -> float:
    """A --sim-speed value: a number, or 'max' (as fast as possible, like 0)."""
    return 0.0 if text.strip().lower() == "max" else float(text)


def register(subparsers) -> None:
    """Add this package's sub-commands to the ``shakerlab`` parser."""
    p = subparsers.add_parser(
        "acquire",
        help="run the protocol on the rig and record the run file",
        description="Run the experiment protocol against the instruments at the configured addresses "
        "(without --config: on a simulated rig started here, in real time) and record every sample "
        "to an HDF5 run file. Ctrl-C ramps the output down and stops; a second Ctrl-C cuts at once. "
        "Exit status: 0 complete, 1 error, 3 a limit tripped, 130 aborted.",
    )
    p.add_argument("--config", type=Path, metavar="RIG.toml", help="rig config (addresses, limits, sensor "
                   "quantities); default: the simulated rig with rig/default_rig.toml's settings")
    p.add_argument("--simulated", action="store_true",
                   help="with --config: run its settings (limits, acquisition, sensor quantities) on a simulated "
                        "rig started here (its addresses replace the config's)")
    p.add_argument("--protocol", type=Path, metavar="PROTOCOL.toml",
                   help="protocol (default: rig/default_protocol.toml)")
    p.add_argument("-o", "--output", type=Path, required=True, help="run file to write (.h5)")
    p.add_argument("--force", action="store_true", help="overwrite the output file")
    p.add_argument("--sim-speed", type=sim_speed, default=1.0, metavar="X",
                   help="simulated rig: simulated time per wall time (1 = real time, 0 or 'max' = as fast as possible)")
    p.add_argument("--seed", type=int, default=0, help="simulated rig: the noise seed")
    p.add_argument("--quiet", action="store_true", help="print only warnings, errors and the summary")
    p.set_defaults(handler=_acquire)
    c = subparsers.add_parser(
        "check-rig",
        help="connect every instrument, drive a calibration tone, check that the two sensors agree",
        description="Connect to the generator, the amplifier and both sensors and read their identities, drive "
        "a small calibration tone ([check] in the rig config) with both sensors aimed at the shaker's base, and "
        "report each sensor's amplitude and their agreement (docs/real-rig.md). Without --config: on a simulated "
        "rig started here, with both simulated sensors on the base. Exit status: 0 passed, 1 a check failed "
        "(the reason is printed), 2 a bad config.",
    )
    c.add_argument("--config", type=Path, metavar="RIG.toml", help="rig config; default: the simulated rig with "
                   "rig/default_rig.toml's settings")
    c.add_argument("--simulated", action="store_true",
                   help="with --config: check its settings on a simulated rig started here")
    c.add_argument("--sim-config", type=Path, metavar="SIM.toml",
                   help="simulated rig: simulator settings (docs/simulator.md), e.g. a sensor's scale error")
    c.add_argument("--sim-speed", type=float, default=1.0, metavar="X",
                   help="simulated rig: simulated time per wall time (1 = real time, 0 = as fast as possible)")
    c.add_argument("--seed", type=int, default=0, help="simulated rig: the noise seed")
    c.add_argument("--json", action="store_true", help="print the report as JSON")
    c.set_defaults(handler=_check_rig)
    register_gui(subparsers)


def _check_rig(args) -> int:
    import json  # heavy: numpy, pymodbus, pyvisa; loaded when the command runs

    from rig.check import check_rig  # heavy: numpy, pymodbus, pyvisa; loaded when the command runs
    from rig.config import load_config  # heavy: numpy, pymodbus, pyvisa; loaded when the command runs
    from rig.session import simulated_rig  # heavy: numpy, pymodbus, pyvisa; loaded when the command runs
    from shakerlab.errors import UserFacingError  # heavy: numpy, pymodbus, pyvisa; loaded when the command runs
    from shakerlab.toml_fields import load_toml  # heavy: numpy, pymodbus, pyvisa; loaded when the command runs

    if not math.isfinite(args.sim_speed) or args.sim_speed < 0:
        raise UserFacingError(f"--sim-speed must be a finite number >= 0 (0: as fast as possible), "
                              f"got {args.sim_speed!r}")
    if args.simulated and args.config is None:
        raise UserFacingError("--simulated applies a --config to the simulated rig; without --config the "
                              "simulated rig is used anyway")
    config = load_config(args.config)
    if args.config is not None and not args.simulated:
        if args.sim_config is not None:
            raise UserFacingError("--sim-config applies to a simulated rig (no --config, or --simulated)")
        report = check_rig(config)
    else:
        sim_config = load_toml(args.sim_config, "simulator config")[0] if args.sim_config else {}
        sensors = sim_config.setdefault("sensors", {})
        if not isinstance(sensors, dict):
            raise UserFacingError(f"{args.sim_config}: [sensors] must be a table")
        sensors.setdefault("tip_on_base", 1.0)  # the documented set-up: both sensors on the base
        speed = None if args.sim_speed == 0 else args.sim_speed
        with simulated_rig(speed=speed, seed=args.seed, sim_config=sim_config, rig_config=config) as (_, sim_cfg):
            report = check_rig(sim_cfg, lockstep=speed is None)
    print(json.dumps(report.as_dict(), indent=2) if args.json else report.text())
    return 0 if report.passed else 1


def _acquire(args) -> int:
    from rig.config import load_config  # heavy: numpy, h5py, Qt; loaded when the command runs
    from rig.console import ConsoleProgress, print_summary, sigint_aborts  # heavy: numpy, h5py, Qt; loaded when the command runs
    from rig.protocol import load_protocol  # heavy: numpy, h5py, Qt; loaded when the command runs
    from rig.session import EXIT_CODES, acquire, simulated_rig  # heavy: numpy, h5py, Qt; loaded when the command runs
    from shakerlab.errors import UserFacingError  # heavy: numpy, h5py, Qt; loaded when the command runs
    from shakerlab.output_files import check_output, refuse_partial  # heavy: numpy, h5py, Qt; loaded when the command runs

    if not math.isfinite(args.sim_speed) or args.sim_speed < 0:
        raise UserFacingError(f"--sim-speed must be a finite number >= 0 (0: as fast as possible), "
                              f"got {args.sim_speed!r}")
    protocol = load_protocol(args.protocol)
    check_output(args.output, overwrite=args.force, what="run file")
    refuse_partial(args.output)
    progress = ConsoleProgress(quiet=args.quiet)
    if args.simulated and args.config is None:
        raise UserFacingError("--simulated applies a --config to the simulated rig; without --config the "
                              "simulated rig is used anyway")
    if args.config is not None and not args.simulated:
        config = load_config(args.config)
        protocol.check_against_limits(config.limits, config.source)
        with sigint_aborts() as hook:
            outcome = acquire(config, protocol, args.output, overwrite=args.force, observers=[progress],
                              on_runner=hook)
    else:
        speed = None if args.sim_speed == 0 else args.sim_speed
        config = load_config(args.config)
        protocol.check_against_limits(config.limits, config.source)
        pace = 'as fast as possible' if speed is None else f'speed {speed:g}'
        print(f"{'no --config' if args.config is None else f'{args.config} on'}: starting the simulated rig ({pace})")
        with simulated_rig(speed=speed, seed=args.seed, rig_config=args.config) as (sim, config), \
                sigint_aborts() as hook:
            outcome = acquire(config, protocol, args.output, lockstep=speed is None, overwrite=args.force,
                              observers=[progress], on_runner=hook,
                              attrs={"simulated": True, "seed": args.seed})
    print_summary(outcome)
    if getattr(outcome, "no_space", None):
        raise UserFacingError(outcome.no_space)
    return EXIT_CODES.get(outcome.status, 1)

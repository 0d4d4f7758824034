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
    p.add_argument("--sim-config", type=Path, metavar="SIM.toml",
                   help="simulated rig: simulator settings (docs/simulator.md), e.g. a concealed effect")
    p.add_argument("--diagnose", action="store_true",
                   help="after the protocol: diagnose the run, record the stage(s) that decide an undecided "
                        "answer into the same file, diagnose again (docs/closed-loop.md)")
    p.add_argument("--auto", action="store_true",
                   help="with --diagnose: record the planned stages without asking (else: asked on a terminal; "
                        "not on a terminal, the plan is printed and the loop stops)")
    p.add_argument("--max-rounds", type=int, default=2, metavar="N",
                   help="with --diagnose: at most N added rounds (default 2)")
    p.add_argument("--json", action="store_true",
                   help="with --diagnose: print one JSON object on stdout (the final diagnosis under 'diagnosis', "
                        "the rounds under 'rounds'); progress goes to stderr")
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
    import sys  # heavy: numpy, h5py, Qt; loaded when the command runs

    from rig.config import load_config  # heavy: numpy, h5py, Qt; loaded when the command runs
    from rig.console import ConsoleProgress, print_summary, sigint_aborts  # heavy: numpy, h5py, Qt; loaded when the command runs
    from rig.protocol import load_protocol  # heavy: numpy, h5py, Qt; loaded when the command runs
    from rig.session import EXIT_CODES, acquire, simulated_rig  # heavy: numpy, h5py, Qt; loaded when the command runs
    from shakerlab.errors import UserFacingError  # heavy: numpy, h5py, Qt; loaded when the command runs
    from shakerlab.output_files import check_output, refuse_partial  # heavy: numpy, h5py, Qt; loaded when the command runs
    from shakerlab.toml_fields import load_toml  # heavy: numpy, h5py, Qt; loaded when the command runs

    if not math.isfinite(args.sim_speed) or args.sim_speed < 0:
        raise UserFacingError(f"--sim-speed must be a finite number >= 0 (0: as fast as possible), "
                              f"got {args.sim_speed!r}")
    for flag, given in (("--auto", args.auto), ("--json", args.json), ("--max-rounds", args.max_rounds != 2)):
        if given and not args.diagnose:
            raise UserFacingError(f"{flag} applies to --diagnose")
    if args.max_rounds < 0:
        raise UserFacingError(f"--max-rounds must be >= 0, got {args.max_rounds}")
    protocol = load_protocol(args.protocol)
    check_output(args.output, overwrite=args.force, what="run file")
    refuse_partial(args.output)
    # with --json, stdout holds the one JSON object; everything for the operator goes to stderr
    stream = sys.stderr if args.json else sys.stdout
    progress = ConsoleProgress(quiet=args.quiet, stream=stream)
    if args.simulated and args.config is None:
        raise UserFacingError("--simulated applies a --config to the simulated rig; without --config the "
                              "simulated rig is used anyway")
    real = args.config is not None and not args.simulated
    if real and args.sim_config is not None:
        raise UserFacingError("--sim-config applies to a simulated rig (no --config, or --simulated)")

    def run(config, lockstep, attrs, texts=None):
        with sigint_aborts() as hook:
            outcome = acquire(config, protocol, args.output, lockstep=lockstep, overwrite=args.force,
                              observers=[progress], on_runner=hook, attrs=attrs, texts=texts)
            print_summary(outcome, stream=stream)
            if getattr(outcome, "no_space", None):
                raise UserFacingError(outcome.no_space)
            if not args.diagnose:
                return EXIT_CODES.get(outcome.status, 1)
            if outcome.status != "complete":
                print(f"not diagnosed: the run ended {outcome.status}", file=stream)
                if args.json:
                    import json  # heavy: numpy, h5py, Qt; loaded when the command runs

                    print(json.dumps({"diagnosis": None, "rounds": [], "stop": "run_failed",
                                      "stop_reason": f"the run ended {outcome.status}: {outcome.reason}",
                                      "run_file": str(outcome.path) if outcome.path else None}))
                return EXIT_CODES.get(outcome.status, 1)
            return _closed_loop(args, config, protocol, lockstep, progress, hook, stream)

    if real:
        config = load_config(args.config)
        protocol.check_against_limits(config.limits, config.source)
        return run(config, False, None)
    speed = None if args.sim_speed == 0 else args.sim_speed
    config = load_config(args.config)
    protocol.check_against_limits(config.limits, config.source)
    sim_config, sim_text = (load_toml(args.sim_config, "simulator config") if args.sim_config else ({}, ""))
    pace = 'as fast as possible' if speed is None else f'speed {speed:g}'
    print(f"{'no --config' if args.config is None else f'{args.config} on'}: starting the simulated rig ({pace})"
          + (f" with {args.sim_config}" if args.sim_config else ""), file=stream)
    with simulated_rig(speed=speed, seed=args.seed, sim_config=sim_config, rig_config=args.config) as (sim, config):
        return run(config, speed is None, {"simulated": True, "seed": args.seed},
                   {"simulator_toml": sim_text} if sim_text else None)


def _closed_loop(args, config, protocol, lockstep, progress, hook, stream) -> int:
    """acquire --diagnose: the loop of rig.closed_loop on the run just recorded; prints its answer."""
    import json  # heavy: recon; loaded when the command runs
    import sys  # heavy: recon; loaded when the command runs

    from rig.closed_loop import ClosedLoop, diagnose_file, record_round  # heavy: recon; loaded when the command runs
    from rig.session import EXIT_CODES  # heavy: recon; loaded when the command runs
    from shakerlab.jsonsafe import clean  # heavy: recon; loaded when the command runs
    from workflows.plausibility import warnings_for  # heavy: recon; loaded when the command runs

    def diagnose_run(path):
        hook(None)      # Ctrl-C while diagnosing cancels the loop (nothing is driven)
        return diagnose_file(path, extra=lambda run: {"warnings": warnings_for(run)})

    outcomes = []

    def record(plan):
        outcome = record_round(config, protocol, args.output, plan, lockstep=lockstep, observers=[progress],
                               on_runner=hook)
        outcomes.append(outcome)
        print_round_summary(outcome, stream)
        return outcome

    def confirm(plan):
        if args.auto:
            return True
        if not (sys.stdin.isatty() and stream.isatty()):
            return False
        print(plan.text(), file=stream)
        print("record these stages into the run file? [y/N] ", end="", file=stream, flush=True)
        answer = sys.stdin.readline()
        return answer.strip().lower() in ("y", "yes")

    def observer(event, payload):
        if event == "diagnosing":
            print(f"closed loop: diagnosing {'the run' if payload['round'] == 0 else 'the extended run'} ...",
                  file=stream, flush=True)
        elif event == "diagnosis":
            sm = payload["summary"]
            print(f"closed loop, round {payload['round']}: {sm['result']}"
                  + (f"; ambiguous: {' / '.join(sm['ambiguous'])}" if sm["ambiguous"] else ""), file=stream)
        elif event == "plan" and (args.auto or args.json):
            print(payload.text(), file=stream)

    loop = ClosedLoop(args.output, config.limits, diagnose=diagnose_run, record=record, confirm=confirm,
                      observer=observer, max_rounds=args.max_rounds)
    result = loop.run()
    if args.json:
        print(json.dumps(clean({"diagnosis": result.diagnosis, "rounds": result.rounds, "stop": result.stop,
                                "stop_reason": result.stop_reason, "run_file": str(args.output),
                                "history": result.result_group})))
    else:
        if result.diagnosis:
            print_diagnosis(result.diagnosis, str(args.output), stream)
        for r in result.rounds:
            print(f"round {r['round']}: {r['why']}; stages added: {', '.join(r['stages_added']) or 'none'}", file=stream)
        print(f"closed loop stopped ({result.stop}): {result.stop_reason}", file=stream)
    last = outcomes[-1].status if outcomes else "complete"
    if result.stop == "cancelled":
        return EXIT_CODES["aborted"]
    return EXIT_CODES.get(last, 1)


def print_round_summary(outcome, stream) -> None:
    print(f"added stages: {outcome.status}" + (f" ({outcome.reason})" if outcome.reason else "")
          + (f"; {outcome.file_note}" if getattr(outcome, "file_note", "") else ""), file=stream)


def print_diagnosis(out: dict, source: str, stream) -> None:
    """The final diagnosis, as `shakerlab diagnose` prints it."""
    p = lambda s="": print(s, file=stream)  # noqa: E731
    p(f"{source}: baseline ({out.get('baseline_kind')})")
    p(out["baseline"])
    for w in out.get("warnings", []) + ([out["baseline_note"]] if out.get("baseline_note") else []):
        p(f"warning: {w}")
    fb, fa = out["fit_before"]["nrmse"], out["fit_after"]["nrmse"]
    for stage in fb:
        p(f"  NRMSE {stage:12s} before {fb[stage]:.4g}  refit {out['fit_before']['refit_nrmse'][stage]:.4g}"
          f"  after {fa[stage]:.4g}")
    for f in out["mismatch"][:8]:
        p(f"  mismatch: {f['kind']} in {f['stage']} {f['region']} size {f['size']:.3g}")
    p(out["result"])
    for m in out["missing_physics"]:
        ps = ", ".join(f"{k} = {v['value']:.4g}" for k, v in m["parameters"].items())
        p(f"  {m['id']}: {m['explanation']} ({ps}); held-out NRMSE "
          f"{m['evidence']['held_out_nrmse_before']:.4g} -> {m['evidence']['held_out_nrmse_after']:.4g}")
    if out["missing_physics"]:
        p("augmented model:\n" + out["fit_after"]["model"])
    else:
        lims = [(c["id"], c["detection_limit"]) for c in out["candidates_tested"]
                if (c.get("detection_limit") or {}).get("value") is not None]
        if lims:
            p("not seen above (detection limits on this record): "
              + ", ".join(f"{cid} {d['parameter']} {d['value']:.3g}" for cid, d in lims))
    if out.get("unexplained_mismatch"):
        p(f"unexplained: {out['unexplained_mismatch']['note']}")

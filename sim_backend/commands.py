"""Sub-commands contributed by ``sim_backend`` (see shakerlab.cli)."""
from __future__ import annotations


def register(subparsers) -> None:
    """Add this package's sub-commands to the ``shakerlab`` parser."""
    sim = subparsers.add_parser("sim", help="the simulated rig (instrument servers on loopback)")
    sim_sub = sim.add_subparsers(dest="sim_command", metavar="SIM_COMMAND")
    serve = sim_sub.add_parser(
        "serve", help="serve all simulated instruments until interrupted",
        description="Start the simulated rig's instruments (signal generator, power amplifier, base and tip "
                    "laser sensors) as servers on this machine and print their addresses, to point "
                    "`shakerlab acquire` or the operator window at them. They speak the real instruments' "
                    "protocols over TCP (and ptys with --pty); Ctrl-C stops them.")
    serve.add_argument("--config", help="simulator config TOML (overrides sim_backend/default_sim.toml)")
    serve.add_argument("--speed", "--sim-speed", dest="speed", default="1.0",
                       help="simulated seconds per wall-clock second (default 1.0 = real time); "
                            "'max' or 0 = lockstep, advanced by sensor fetches (--sim-speed as elsewhere)")
    serve.add_argument("--seed", type=int, default=0, help="noise seed (default 0)")
    serve.add_argument("--host", default="127.0.0.1", help="interface to bind (default 127.0.0.1)")
    serve.add_argument("--pty", action="store_true", help="also serve the line instruments on ptys")
    serve.add_argument("--duration", type=float, default=None,
                       help="stop after this many wall-clock seconds (default: until Ctrl-C)")
    for name in ("generator", "amplifier", "sensor-base", "sensor-tip"):
        serve.add_argument(f"--{name}-port", type=int, default=0,
                           help=f"TCP port of the {name.replace('-', ' ')} (default: any free port)")
    serve.set_defaults(handler=_serve)
    sim.set_defaults(handler=lambda args: sim.print_help() or 2)


def _serve(args) -> int:
    import sys  # heavy: numba physics; loaded when the command runs
    import time  # heavy: numba physics; loaded when the command runs

    from shakerlab.errors import UserFacingError  # heavy: numba physics; loaded when the command runs
    from sim_backend.rig import SimulatedRig  # heavy: numba physics; loaded when the command runs

    if args.speed.strip().lower() in ("max", "0", "0.0"):
        speed = None
    else:
        try:
            speed = float(args.speed)
        except ValueError:
            raise UserFacingError(f"--speed must be a positive number, 0 or 'max', got {args.speed!r}") from None
        if not speed > 0:
            raise UserFacingError(f"--speed must be a positive number, 0 or 'max', got {args.speed!r}")
    ports = {"generator": args.generator_port, "amplifier": args.amplifier_port,
             "sensor_base": args.sensor_base_port, "sensor_tip": args.sensor_tip_port}
    for name, port in ports.items():
        if not 0 <= port <= 65535:
            raise UserFacingError(f"--{name.replace('_', '-')}-port must be 0..65535, got {port}")
    if not _loopback(args.host):
        print(f"warning: --host {args.host} serves the simulated instruments beyond this machine: anyone who "
              f"reaches this host can drive the simulated amplifier (ENABLE, gain, amplitude). Keep instrument "
              f"networks isolated (docs/acquisition.md, 'Instrument networks').", file=sys.stderr, flush=True)
    try:
        rig = SimulatedRig(args.config, speed=speed, seed=args.seed, pty=args.pty, host=args.host,
                           ports=ports)
        rig.start()
    except OSError as exc:
        raise UserFacingError(f"cannot start the simulated instruments: {exc}") from None
    try:
        ptys = rig.pty_paths
        for name, url in rig.addresses.items():
            hostport = url.removeprefix("socket://")
            line = f"{name:12s} {hostport}"
            if name in ptys:
                line += f"  pty {ptys[name]}"
            print(line, flush=True)
        mode = "lockstep (advanced by sensor fetches)" if speed is None else f"speed {speed:g}x real time"
        print(f"simulated rig running, {mode}; Ctrl-C to stop", file=sys.stderr, flush=True)
        t_end = None if args.duration is None else time.monotonic() + args.duration
        while t_end is None or time.monotonic() < t_end:
            time.sleep(0.1)
    finally:
        rig.stop()
    return 0


def _loopback(host: str) -> bool:
    """True when ``host`` binds the loopback interface only (127.0.0.0/8, ::1, localhost)."""
    import ipaddress  # lazy: only for sim serve

    if host in ("localhost", "ip6-localhost"):
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False

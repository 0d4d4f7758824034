"""The ``shakerlab`` command line.

Each package contributes its own sub-commands through a ``commands`` module
with a ``register(subparsers)`` function; this module only assembles them.
Command modules must stay light at import time (heavy imports go inside the
handlers) so that ``shakerlab --help`` is instant.
"""
from __future__ import annotations

import argparse
import atexit
import contextlib
import ctypes
import importlib
import json
import os
import sys

from shakerlab import __version__, progress_view
from shakerlab.errors import Terminated, UserFacingError
from shakerlab.output_files import terminate_raises

# glibc's mallopt parameter number for the most arenas (malloc.h: M_ARENA_MAX)
M_ARENA_MAX = -8

COMMAND_MODULES = (
    "workflows.commands",
    "sim_backend.commands",
    "rig.commands",
    "shakerlab.import_command",
)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="shakerlab",
        description="Shaker-rig experiments on hysteretic structures.",
    )
    parser.add_argument("--version", action="version", version=f"shakerlab {__version__}")
    subparsers = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in COMMAND_MODULES:
        importlib.import_module(name).register(subparsers)
    return parser


def quiet_exit_on_terminal() -> None:
    """At exit, once Python has flushed its output, a terminal on stdout is detached: the JIT compiler's
    library (LLVM, through numba) resets the terminal's colour in its static destructors, which would
    leave a stray escape code after every command's last line. Pipes and files get no such code."""
    try:
        if not os.isatty(1):
            return
    except OSError:
        return

    def detach():
        with contextlib.suppress(OSError, ValueError):
            sys.stdout.flush()
            devnull = os.open(os.devnull, os.O_WRONLY)
            os.dup2(devnull, 1)

    atexit.register(detach)


def one_malloc_arena() -> None:
    """Every thread of this process allocates from glibc's main arena (mallopt M_ARENA_MAX = 1, as
    the MALLOC_ARENA_MAX variable sets it); elsewhere nothing. A thread's own arena keeps what it
    freed for that thread alone: the fits' Jacobian threads (recon.threads) each held their own
    tens of MiB beside the main thread's free memory, about 45 MiB of `diagnose`'s peak on a
    10 kHz run. The fits allocate once per simulation, so one arena costs no measurable time."""
    try:
        libc = ctypes.CDLL("libc.so.6")
        libc.mallopt(M_ARENA_MAX, 1)
    except (OSError, AttributeError):      # not glibc: its own allocator's behaviour stands
        pass


def one_blas_thread() -> None:
    """BLAS (OpenBLAS, MKL) and OpenMP run one thread each unless the user's environment says
    otherwise; set before numpy is first imported (this module imports none). The fits' linear
    algebra is on tall, narrow matrices (thousands of rows, a few columns), where a BLAS thread pool
    spends its time waking and spinning, and the fits run their own threads (recon.threads) and
    Dask its own workers beside it: `diagnose` c01 took 4 % less CPU and wall time with one BLAS
    thread (5 paired runs on 2 cores), and the answers are the same (tests/test_determinism.py)."""
    for var in ("OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "OMP_NUM_THREADS"):
        os.environ.setdefault(var, "1")


def main(argv: list[str] | None = None) -> int:
    one_blas_thread()       # before numpy is imported
    one_malloc_arena()      # before any thread allocates
    try:
        return _main(argv)
    finally:
        quiet_exit_on_terminal()    # registered last, so it runs before the libraries' own exit handlers


def _main(argv: list[str] | None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "handler", None):
        parser.print_help()
        return 2
    terminate_raises()      # SIGTERM cleans up like Ctrl-C (acquire installs its own ramp-down handler)
    try:
        try:
            return int(args.handler(args) or 0)
        finally:
            progress_view.stop()    # before any message below, so it is not drawn over
    except Terminated:
        print(f"shakerlab {args.command}: terminated (SIGTERM); files being written were discarded, existing "
              f"files left as they were", file=sys.stderr)
        return 143
    except KeyboardInterrupt:
        print(f"shakerlab {args.command}: interrupted (Ctrl-C); files being written were discarded, existing "
              f"files left as they were", file=sys.stderr)
        return 130
    except UserFacingError as exc:
        print(f"shakerlab {args.command}: error: {exc}", file=sys.stderr)
        if getattr(args, "json", False):
            # A command asked for JSON answers in JSON even when it refuses: a script reading stdout gets one
            # object whatever happened (the exit status, 2, and the message on stderr are as without --json).
            print(json.dumps(refusal_json(args.command, exc)))
        return 2


def refusal_json(command: str, exc: UserFacingError) -> dict:
    """The one JSON object a --json command prints when it refuses: the error and its kind."""
    return {"error": str(exc), "error_kind": type(exc).__name__, "command": command, "exit_code": 2}


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())

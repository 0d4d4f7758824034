"""Sub-commands of the application layer (see shakerlab.cli): reconstruct, report, reprocess, diagnose, backbone,
demo.

Only the parsers live here, so ``shakerlab --help`` stays instant; the handlers (workflows.handlers) are
imported when a command runs."""
from __future__ import annotations

import argparse
import importlib
from pathlib import Path

from shakerlab import progress_view
from shakerlab.options import output_option


def _handler(name: str, module: str = "workflows.handlers", progress: bool = False):
    """The handler ``<module>.<name>``, imported on first call. With ``progress`` the command's
    progress line starts at once (loading the numerical libraries takes seconds), unless --quiet."""

    def run(args) -> int:
        if progress:
            progress_view.start("loading the numerical libraries", quiet=getattr(args, "quiet", False))
        # the module is heavy (numpy, scipy, h5py, recon): imported only when a command runs
        return getattr(importlib.import_module(module), name)(args)

    run.__name__ = name
    return run


def register(subparsers) -> None:
    """Add this package's sub-commands to the ``shakerlab`` parser."""
    p = subparsers.add_parser(
        "reconstruct",
        help="identify the hysteretic governing equation from a run file",
        description="Reconstruct y'' + c y' + k y + fn(y, y') + z = u with Bouc-Wen z from a run "
                    "(.h5 or .npz with stages 'linear', 'nonlinear', optionally 'validation'). "
                    "Everything is per unit mass.",
    )
    p.add_argument("run", metavar="RUN", help="run file (.h5 or .npz)")
    p.add_argument("--json", action="store_true", help="print one JSON object (machine-readable)")
    output_option(p, "--plots", "write PNG overlays (time history, hysteresis loop) to DIR")
    p.add_argument("--library-order", metavar="Q", type=int, default=5,
                   help="highest monomial degree of fn (default 5)")
    p.add_argument("--save-model", metavar="PATH", help="write the identified model as JSON to PATH")
    p.add_argument("--force", action="store_true",
                   help="replace an existing --save-model file or -o files (never a run file)")
    p.add_argument("--no-polish", action="store_true", help="skip the output-error polish (equation-error estimate only)")
    p.add_argument("--form", choices=("joint", "weak", "ab"), default="joint",
                   help="nonlinear step: pointwise agent model on AB and CD (joint, default), the weak form "
                        "(needs no third derivative; holds to 40 dB SNR, see docs/method.md) or the paper's AB-only form")
    p.add_argument("--uncertainty", action="store_true",
                   help="add 95%% intervals of every parameter (key 'uncertainty'; see docs/reprocessing.md)")
    p.add_argument("--no-uncertainty", dest="uncertainty", action="store_false",
                   help="no parameter intervals (the default here)")
    quiet_option(p)
    p.add_argument("--drive", action="store_true",
                   help="the force channel is the exciter's drive (an amplifier voltage), not a measured force: "
                        "also fit the exciter's even-order distortion and low-frequency roll-off, kept when it "
                        "predicts the validation stage better (force excitation; docs/real-data.md)")
    _inertia_option(p)
    p.set_defaults(handler=_handler("reconstruct_command", progress=True))
    register_reprocessing(subparsers)
    register_diagnosis(subparsers)
    register_backbone(subparsers)
    register_demo(subparsers)


# --- offline reprocessing: `report` and `reprocess` (workflows/report.py, workflows/batch.py) ---------------

def register_reprocessing(subparsers) -> None:
    p = subparsers.add_parser(
        "report",
        help="reconstruct a run and write an HTML report (PNG figures, JSON, intervals)",
        description="Reconstruct RUN, compute parameter intervals, and write DIR/index.html (self-contained, "
                    "figures embedded), the figures as PNG and DIR/result.json. The result is written back "
                    "into the run file (entry/results/reconstruction_NNN) unless the same settings are stored.",
    )
    p.add_argument("run", metavar="RUN", help="run file (.h5; .npz works but holds no results)")
    p.add_argument("-o", "--output", metavar="DIR", required=True,
                   help="report directory (created; an existing non-empty one needs --force)")
    p.add_argument("--force", action="store_true",
                   help="write into an existing report directory (its report files are replaced, others kept)")
    _common_recon_options(p)
    p.add_argument("--no-write-back", action="store_true", help="do not write the result into the run file")
    p.add_argument("--term-models", metavar="N", type=int, default=0,
                   help="term-selection ensemble size (row-subsampled reselections, ~1 s each; default 0: off)")
    p.add_argument("--json", action="store_true", help="print the result JSON instead of a summary")
    quiet_option(p)
    _inertia_option(p)
    p.set_defaults(handler=_handler("report_command", progress=True))

    p = subparsers.add_parser(
        "reprocess",
        help="reconstruct many run files in parallel on Dask (summary table, results written back)",
        description="Reconstruct every run matching the patterns (quote them: 'runs/*.h5') on a local Dask "
                    "cluster or an existing scheduler. Runs already processed with the same settings are "
                    "skipped; a bad run is reported with its reason and the batch goes on. Prints a summary "
                    "table and writes it as CSV.",
    )
    p.add_argument("patterns", metavar="RUNS", nargs="+", help="run files or glob patterns")
    p.add_argument("--scheduler", metavar="ADDRESS", help="address of a running Dask scheduler (tcp://host:port)")
    p.add_argument("--workers", metavar="N", type=int, default=2, help="local cluster worker processes (default 2)")
    p.add_argument("--threads", action="store_true", help="local cluster with threads instead of processes")
    p.add_argument("--serial", action="store_true", help="a plain loop in this process (no Dask)")
    p.add_argument("--csv", metavar="PATH", default="reprocess_summary.csv",
                   help="summary table as CSV (default reprocess_summary.csv)")
    p.add_argument("--diagnose", action="store_true", help="also run the mismatch diagnosis on each run")
    p.add_argument("--force", action="store_true", help="reprocess runs already processed with the same settings")
    p.add_argument("--no-write-back", action="store_true", help="do not write results into the run files")
    p.add_argument("--quiet", action="store_true", help="no progress on stderr")
    p.add_argument("--term-models", metavar="N", type=int, default=0,
                   help="term-selection ensemble size per run (row-subsampled reselections; default 0: off)")
    _common_recon_options(p)
    p.set_defaults(handler=_handler("reprocess_command", progress=True))


def _common_recon_options(p) -> None:
    p.add_argument("--library-order", metavar="Q", type=int, default=5, help="highest monomial degree of fn (default 5)")
    p.add_argument("--no-polish", action="store_true", help="skip the output-error polish")
    p.add_argument("--no-uncertainty", action="store_true", help="skip the parameter intervals")
    p.add_argument("--uncertainty", dest="no_uncertainty", action="store_false",
                   help="compute the parameter intervals (the default)")
    p.add_argument("--form", choices=("joint", "weak", "ab"), default="joint",
                   help="nonlinear step, as reconstruct --form (default joint)")
    p.add_argument("--resamples", metavar="B", type=int, default=200,
                   help="ensemble members for the intervals (default 200)")
    p.add_argument("--drive", action="store_true",
                   help="the force channel is the exciter's drive (an amplifier voltage): also fit the exciter "
                        "(as reconstruct --drive; force excitation)")


# --- mismatch diagnosis: `diagnose` (recon/diagnosis/, docs/diagnosis.md) -----------------------------

def register_diagnosis(subparsers) -> None:
    p = subparsers.add_parser(
        "diagnose",
        help="locate where a model and a recording disagree, name the missing physics, show the fit improve",
        description="Compare a model's simulation with RUN, locate the mismatch (time, frequency, state plane, "
                    "channel), fit every candidate from the physics catalog as an augmented model and rank them "
                    "on held-out data (validation stage, else the last 30 % of each stage; also the last 30 % of a stage "
                    "whose peak the validation stages reach less than 0.4 of).",
    )
    p.add_argument("run", metavar="RUN", help="run file (.h5 or .npz)")
    p.add_argument("--baseline", default="paper", metavar="paper|linear|MODEL.json",
                   help="model to test: 'paper' (reconstructed from RUN, default), 'linear', a saved model JSON, or "
                        "a component test's law JSON (reconstruct --save-model of a constitutive run: its mass "
                        "and support are fitted on RUN)")
    p.add_argument("--json", action="store_true", help="print one JSON object (machine-readable)")
    output_option(p, "--report", "write PNG figures and diagnosis.json to DIR")
    p.add_argument("--save-model", metavar="PATH", help="write the augmented model as JSON to PATH")
    p.add_argument("--candidates", type=_id_list, metavar="ID[,ID...]",
                   help="fit only these candidates of the catalog (default: every one that applies; the ids "
                        "are docs/diagnosis.md's catalog, e.g. coulomb_friction,channel_delay)")
    p.add_argument("--force", action="store_true",
                   help="replace an existing --save-model file or -o files (never a run file)")
    quiet_option(p)
    p.set_defaults(handler=_handler("diagnose_command", progress=True))


def _id_list(text: str) -> list[str]:
    ids = [x.strip() for x in text.split(",") if x.strip()]
    if not ids:
        raise argparse.ArgumentTypeError("give at least one candidate id, comma-separated")
    return ids


# --- amplitude dependence from a ring-down: `backbone` (recon/backbone.py, workflows/backbone.py) ---------

def register_backbone(subparsers) -> None:
    p = subparsers.add_parser(
        "backbone",
        help="frequency and damping against amplitude from a stage's ring-down (measured, and as a model predicts)",
        description="Band-pass a stage's response around one mode, read the instantaneous frequency and decay "
                    "rate of its analytic signal, and tabulate them against the envelope. With --model, the same "
                    "for the model's simulation of the stage (docs/real-data.md).",
    )
    p.add_argument("run", metavar="RUN", help="run file (.h5 or .npz)")
    p.add_argument("--stage", help="stage to read (default: the first validation stage, else the last)")
    p.add_argument("--mode-hz", type=float, help="the mode's frequency (default: the model's sqrt(K)/2 pi with "
                                                 "--model, else the peak of the stage's response spectrum)")
    p.add_argument("--from", dest="t_from", type=float, metavar="S", help="read from S seconds after the stage's start")
    p.add_argument("--to", dest="t_to", type=float, metavar="S", help="read up to S seconds after the stage's start")
    p.add_argument("--band", type=float, default=0.25, help="half-width of the band-pass, relative (default 0.25)")
    p.add_argument("--bins", type=int, default=8, help="amplitude bins (default 8)")
    p.add_argument("--model", metavar="MODEL.json", help="a saved model (reconstruct --save-model) to compare")
    p.add_argument("--json", action="store_true", help="print one JSON object (machine-readable)")
    p.set_defaults(handler=_handler("backbone_command", "workflows.backbone"))


# --- the whole experiment on an embedded simulated rig: `demo` (workflows/demo.py) ---------------------

def register_demo(subparsers) -> None:
    d = subparsers.add_parser(
        "demo",
        help="the whole experiment on an embedded simulated rig: record, reconstruct, report",
        description="Start a simulated TMP-origami shaker rig, run the protocol on it (as fast as possible), "
        "record the run file, reconstruct the governing equation, print it with the validation error "
        "and the simulator's true parameters, and write a report with plots.",
    )
    d.add_argument("-o", "--output", type=Path, default=Path("shakerlab-demo"), metavar="DIR",
                   help="report directory (default ./shakerlab-demo/)")
    d.add_argument("--realtime", action="store_true", help="run the simulated rig in real time")
    d.add_argument("--protocol", type=Path, metavar="PROTOCOL.toml", help="protocol (default: the shipped one)")
    d.add_argument("--seed", type=int, default=0, help="noise seed of the simulated rig")
    d.add_argument("--force", action="store_true", help="replace the files of an existing output folder")
    d.add_argument("--quiet", action="store_true", help="print only warnings, errors and the results")
    d.set_defaults(handler=_handler("demo_command"))


def quiet_option(p) -> None:
    p.add_argument("--quiet", action="store_true", help="no progress on stderr")


def _inertia_option(p) -> None:
    p.add_argument("--inertia", metavar="none|fit|KG", default="none",
                   help="component tests only (docs/constitutive.md): the inertia of the moving parts, a term "
                        "m x'' with m fitted ('fit') or known (a mass in kg); default none")

"""Reprocess many run files in parallel on Dask (``shakerlab reprocess``).

    from workflows.batch import BatchSettings, run_batch, write_csv, format_table
    rows = run_batch(paths, BatchSettings(workers=2))        # one dict per run
    write_csv(rows, "summary.csv"); print(format_table(rows))

Each run is one task, :func:`process_run`, which never raises: a bad file
(unreadable, not a run file, a stage missing, a recording too short, ...)
comes back as a row with ``status = "failed"`` and the reason, and the batch
goes on. A good run is reconstructed (:func:`recon.estimator.pipeline.reconstruct`),
its parameter intervals computed (:mod:`recon.output_error.uncertainty`) and the result
written back into the run file as a new ``entry/results/reconstruction_NNN``
group holding a *settings hash* (attribute ``settings_hash`` and key
``reprocess.settings_hash`` of the payload). A later batch with the same
settings finds the hash and skips the run (``status = "skipped"``, the
stored parameters are reported again). Files not closed cleanly are
processed but never written (``written = false`` and a note).

The scheduler is a ``dask.distributed.LocalCluster`` (``workers`` processes,
one thread each: the numba kernels and numpy hold the GIL in places, so
processes scale better) unless the address of a running scheduler is given.
"""
from __future__ import annotations

import contextlib
import csv
import glob
import hashlib
import importlib.util
import json
import logging
import os
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

from recon import ReconSettings, reconstruct
from recon import progress as recon_progress
from recon.estimator.adequacy import verdict_summary
from recon.constitutive.estimator import ConstitutiveSettings, reconstruct_constitutive
from recon.constitutive.output_error import intervals
from recon.constitutive.signals import component_signals
from recon.output_error.uncertainty import (UncertaintySettings, parameter_intervals, reconstruct_capturing,
                                            term_inclusion)
from recon.testing.truth import sdof_run
from recon.threads import thread_count
from shakerlab import __version__
from shakerlab.errors import UserFacingError
from shakerlab.jsonsafe import clean
from shakerlab.modes import CONSTITUTIVE, run_mode
from shakerlab.runfile.reader import load_run
from shakerlab.runfile.results import find_result, store_result
from shakerlab.runfile.writer import RunWriter
from shakerlab.words import duration_text, nrmse_text

RESULT_KIND = "reconstruction"
PARAMS = ("c_m", "k_m", "alpha_m", "gamma", "delta", "inv_m",
          # a component test's law (constitutive mode, recon.constitutive), in N, m, s
          "c", "k", "alpha", "f0", "mass", "c1", "alpha1", "eta")
FN_KEYS = ("fn_m", "fn")      # a structure's fn per unit mass, a law's in N


@dataclass
class BatchSettings:
    recon: dict = field(default_factory=dict)        # recon.estimator.pipeline.ReconSettings fields
    uncertainty: bool = True
    uncertainty_settings: dict = field(default_factory=dict)   # recon.output_error.uncertainty.UncertaintySettings fields
    term_models: int = 0                              # > 0: term-selection ensemble (recon.output_error.uncertainty.term_inclusion)
    diagnose: bool = False
    write_back: bool = True
    force: bool = False                               # reprocess even when the settings hash is stored
    workers: int = 2
    scheduler: str | None = None                      # address of a running scheduler
    processes: bool = True                            # LocalCluster workers as processes (False: threads)
    connect_timeout: float = 10.0                     # seconds to reach --scheduler

    def job(self) -> dict:
        """What a worker needs (JSON-safe)."""
        return {"recon": dict(self.recon), "uncertainty": self.uncertainty,
                "uncertainty_settings": dict(self.uncertainty_settings), "term_models": int(self.term_models),
                "diagnose": self.diagnose,
                "write_back": self.write_back, "force": self.force}


def settings_hash(job: dict) -> str:
    """Hash of everything that decides a reconstruction's numbers: the recon settings with
    their defaults filled in, the uncertainty settings, and the software version."""

    rs = ReconSettings(**job.get("recon", {})).to_dict()
    if not rs.get("drive"):     # added later, off by default: the hash of every earlier setting is unchanged
        rs.pop("drive", None)
    us = UncertaintySettings(**job.get("uncertainty_settings", {})).to_dict() if job.get("uncertainty") else None
    text = json.dumps({"recon": rs, "uncertainty": us, "software": __version__,
                       **({"term_models": int(job["term_models"])} if job.get("term_models") else {})},
                      sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def _row(path, status, **kw) -> dict:
    row = {"run": str(path), "status": status, "reason": "", "written": False, "group": "", "seconds": 0.0,
           "parameters": {}, "intervals": {}, "nrmse": None, "validation_stage": None, "notes": [],
           "verdict": "", "verdict_text": ""}
    row.update(kw)
    return row


def _fill(row: dict, payload: dict) -> dict:
    row["parameters"] = payload.get("parameters", {})
    row["intervals"] = (payload.get("uncertainty") or {}).get("intervals", {})
    val = payload.get("validation") or {}
    row["nrmse"] = val.get("nrmse")
    row["validation_stage"] = val.get("stage")
    if payload.get("adequacy"):
        v = verdict_summary(payload["adequacy"])
        row["verdict"], row["verdict_text"] = v["label"], v["text"]
    return row


def refuse_drive_for_component_test(drive: bool, source) -> None:
    """--drive models the exciter before a structure; a component test's force is measured."""
    if drive:
        raise UserFacingError(f"--drive is for a structure driven through an exciter; {source} is a "
                              f"component test (its force is measured)")


def reconstruct_payload(run, job: dict):
    """(result, payload) for one run: the reconstruction's JSON, plus ``uncertainty`` when asked."""

    if run_mode(run) == CONSTITUTIVE:      # a component test: its force law (docs/constitutive.md)
        rs = job.get("recon", {})
        refuse_drive_for_component_test(rs.get("drive", False), run.source)
        cs = ConstitutiveSettings(library_order=rs.get("library_order", 5), polish=rs.get("polish", True))
        result = reconstruct_constitutive(run, cs)
        payload = result.to_dict()
        if job.get("uncertainty"):
            sig = component_signals(run.stage(cs.fit_stage))
            iv = intervals(result.law, [sig], fit_rate=cs.fit_rate)
            q = {k: [v["low"], v["high"]] for k, v in iv["parameters"].items() if not k.startswith("fn:")}
            q["fn"] = {k[3:]: [v["low"], v["high"]] for k, v in iv["parameters"].items() if k.startswith("fn:")}
            payload["uncertainty"] = dict(iv, intervals=q)
        return result, clean(payload)
    settings = ReconSettings(**job.get("recon", {}))
    if job.get("term_models"):

        result, problem = reconstruct_capturing(run, settings)
        payload = result.to_dict()
        payload["term_selection"] = term_inclusion(problem, n_models=int(job["term_models"]))
    else:
        result = reconstruct(run, settings)
        payload = result.to_dict()
    if job.get("uncertainty"):

        payload["uncertainty"] = parameter_intervals(result.model, run,
                                                     UncertaintySettings(**job.get("uncertainty_settings", {})))
    return result, clean(payload)


PROGRESS_TOPIC = "shakerlab-progress"      # a worker's steps, forwarded to the client (TextProgress)


def process_run(path: str, job: dict) -> dict:
    """Reconstruct one run file; never raises (failures are rows with a reason). On a Dask worker its
    steps (recon.progress) go to the client as events of PROGRESS_TOPIC."""
    worker = _worker()
    if worker is None:
        return _process_run(path, job)
    name = Path(path).name

    def forward(u: recon_progress.Update) -> None:
        worker.log_event(PROGRESS_TOPIC, {"run": name, "text": u.text, "fraction": u.fraction})

    with recon_progress.reporting(forward):
        return _process_run(path, job)


def _worker():
    """The Dask worker running this task, None outside one."""
    from dask.distributed import get_worker  # heavy: Dask, loaded in a batch only (1-2 s of start-up)
    try:
        return get_worker()
    except ValueError:
        return None


def _process_run(path: str, job: dict) -> dict:
    t0 = time.perf_counter()
    path = Path(path)
    try:
        digest = settings_hash(job)
        is_h5 = path.suffix in (".h5", ".hdf5", ".nxs")
        if is_h5 and not job.get("force") and path.exists():
            try:
                hit = find_result(path, RESULT_KIND, digest)
            except UserFacingError:
                hit = None            # unreadable: load_run below names the problem
            if hit is not None:
                return _fill(_row(path, "skipped", reason=f"already processed with these settings ({hit[0]})",
                                  group=hit[0], settings_hash=digest, seconds=time.perf_counter() - t0), hit[1])
        run = load_run(path)
        recon_progress.step("reconstruction", share=0.5 if job.get("diagnose") else 1.0)
        result, payload = reconstruct_payload(run, job)
        payload["reprocess"] = {"settings_hash": digest, "settings": job, "software": f"shakerlab {__version__}"}
        row = _fill(_row(path, "ok", settings_hash=digest), payload)
        if job.get("diagnose"):
            recon_progress.step("diagnosis", share=0.5)
            row["diagnosis"] = _diagnose(run, result, path if is_h5 else None, row)
        if job.get("write_back", True):
            group, note = store_result(path, RESULT_KIND, payload, text=str(result.model), settings_hash=digest)
            if group is None:
                row["notes"].append(note)
            else:
                row["written"], row["group"] = True, group
        row["seconds"] = time.perf_counter() - t0
        return row
    except UserFacingError as exc:
        return _row(path, "failed", reason=str(exc), seconds=time.perf_counter() - t0)
    except Exception as exc:  # noqa: BLE001 - one bad run must not stop the batch
        return _row(path, "failed", reason=f"{type(exc).__name__}: {exc}", seconds=time.perf_counter() - t0)


def diagnosis_available() -> bool:

    try:
        return importlib.util.find_spec("recon.diagnosis.diagnose") is not None
    except ModuleNotFoundError:
        return False


def _diagnose(run, result, path, row) -> str:
    if not diagnosis_available():
        row["notes"].append("diagnosis unavailable (recon.diagnosis is not installed)")
        return "unavailable"
    try:
        from recon.diagnosis.diagnose import diagnose  # optional: diagnosis may be left out of an install
        from recon.diagnosis.wording import diagnosis_text  # optional: as recon.diagnosis.diagnose

        d = diagnose(run, baseline=result.model).to_dict()
    except Exception as exc:  # noqa: BLE001 - a failed diagnosis leaves the reconstruction valid
        row["notes"].append(f"diagnosis failed: {exc}")
        return "failed"
    if path is not None:
        store_result(path, "diagnosis", clean(d), text=str(d.get("result", "")))
    return diagnosis_text(d)


# ---------------------------------------------------------------------------
# progress, scheduling
# ---------------------------------------------------------------------------

class TextProgress:
    """Progress of a batch on stderr: a line per finished run, and the runs in flight with their
    current step (from the workers' PROGRESS_TOPIC events, or this process's own steps in a plain
    loop) through a :class:`workflows.progress_line.ProgressLine` (``line``; None: nothing shown)."""

    def __init__(self, total: int, stream=None, width: int = 30, enabled: bool = True, line=None):
        self.total, self.enabled = total, enabled
        self.line = line if enabled else None
        self.done = 0
        self.counts = {"ok": 0, "skipped": 0, "failed": 0}
        self.t0 = time.monotonic()
        self.running: dict[str, tuple[str, float]] = {}     # run name: (its step, its fraction)
        self.finished: set[str] = set()

    def update(self, row: dict) -> None:
        """One run finished."""
        self.done += 1
        self.counts[row["status"]] = self.counts.get(row["status"], 0) + 1
        name = Path(row["run"]).name
        self.running.pop(name, None)
        self.finished.add(name)
        if self.line is None:
            return
        what = row["status"] + (f", {nrmse_text(row['nrmse'])} NRMSE" if row["status"] == "ok" else "")
        what += f", {row['verdict']}" if row.get("verdict") else ""
        self.line.note(f"run {self.done} of {self.total} done: {name}: {what} ({duration_text(row.get('seconds', 0))}); "
                       f"ok {self.counts['ok']}, skipped {self.counts['skipped']}, failed {self.counts['failed']}")
        self._show()

    def event(self, event) -> None:
        """A worker's step (a PROGRESS_TOPIC event: (timestamp, {"run", "text", "fraction"}))."""
        msg = event[1] if isinstance(event, tuple) else event
        if msg["run"] in self.finished:
            return              # a late event of a run already done
        self.running[msg["run"]] = (msg["text"], float(msg["fraction"]))
        self._show()

    def status(self, text: str) -> None:
        """What the batch does besides its runs (starting or closing the cluster)."""
        if self.line is not None:
            self.line.update(recon_progress.Update(text, self.done / max(self.total, 1),
                                                   time.monotonic() - self.t0, None))

    def _show(self) -> None:
        if self.line is None:
            return
        if self.done >= self.total:
            self.status(f"all {self.total} runs done; closing")
            return
        frac = (self.done + sum(f for _, f in self.running.values())) / max(self.total, 1)
        busy = "; ".join(f"{n} [{100 * f:.0f} %] {t}" for n, (t, f) in self.running.items())
        text = f"{self.done} of {self.total} runs done" + (f"; running {busy}" if busy else "")
        elapsed = time.monotonic() - self.t0
        left = elapsed * (1 - frac) / frac if frac >= recon_progress.MIN_FRACTION_FOR_ESTIMATE else None
        self.line.update(recon_progress.Update(text, frac, elapsed, left))


def expand(patterns: list[str]) -> list[str]:
    """Glob patterns (quoted on the command line so the shell leaves them) to a sorted, unique list."""

    out = []
    for pat in patterns:
        hits = sorted(glob.glob(pat, recursive=True))
        if not hits:
            if any(c in pat for c in "*?["):
                raise UserFacingError(f"no run file matches {pat!r}")
            hits = [pat]      # a plain name: process_run reports it if it does not exist
        out.extend(h for h in hits if h not in out)
    return out


def run_loop(paths: list[str], settings: BatchSettings, progress: TextProgress | None = None) -> list[dict]:
    """The plain loop (no Dask): same rows, same order as ``paths`` (duplicates once)."""
    paths = list(dict.fromkeys(str(p) for p in paths))
    rows = []
    for i, p in enumerate(paths):
        recon_progress.step(f"run {i + 1} of {len(paths)}: {Path(p).name}", share=1.0 / len(paths))
        rows.append(process_run(str(p), settings.job()))
        if progress:
            progress.update(rows[-1])
    return rows


def run_batch(paths: list[str], settings: BatchSettings | None = None, progress: TextProgress | None = None) -> list[dict]:
    """Process ``paths`` on Dask; rows come back in the order of ``paths`` (a path given twice is
    processed once: two tasks must never write into the same file)."""
    s = settings or BatchSettings()
    paths = list(dict.fromkeys(str(p) for p in paths))
    if s.workers < 1:
        raise UserFacingError(f"--workers must be at least 1, got {s.workers}")

    from dask.distributed import Client, LocalCluster, as_completed  # heavy: Dask, loaded in a batch only

    cluster = None
    try:
        if s.scheduler:
            try:
                client = Client(s.scheduler, timeout=f"{s.connect_timeout}s")
            except (OSError, TimeoutError, ValueError) as exc:
                raise UserFacingError(f"--scheduler {s.scheduler}: cannot connect ({exc})") from None
        else:
            # worker processes share the cores: each one's fits take its share of threads
            # (recon/threads.py; a user's SHAKERLAB_THREADS is kept)
            extra = ({"env": {"SHAKERLAB_THREADS": os.environ.get("SHAKERLAB_THREADS")
                              or str(max(1, thread_count() // s.workers))}} if s.processes else {})
            # warnings of the cluster's own (a worker slow to stop is killed at the end) are not the batch's
            if progress:
                progress.status(f"starting a local Dask cluster ({s.workers} workers)")
            cluster = LocalCluster(n_workers=s.workers, threads_per_worker=1, processes=s.processes,
                                   dashboard_address=":0", host="127.0.0.1", silence_logs=logging.ERROR, **extra)
            client = Client(cluster)
        with client:
            if progress:
                client.subscribe_topic(PROGRESS_TOPIC, progress.event)
            job = s.job()
            futures = [client.submit(process_run, str(p), job, pure=False, key=f"reprocess-{i}-{Path(p).name}")
                       for i, p in enumerate(paths)]
            index = {f.key: i for i, f in enumerate(futures)}
            rows: list[dict | None] = [None] * len(paths)
            for fut in as_completed(futures):
                i = index[fut.key]
                try:
                    row = fut.result()
                except Exception as exc:  # noqa: BLE001 - e.g. a worker killed while running this run
                    row = _row(paths[i], "failed", reason=f"worker error: {type(exc).__name__}: {exc}")
                rows[i] = row
                if progress:
                    progress.update(row)
            return rows
    finally:
        if cluster is not None:
            with _quiet_logs("distributed"):
                cluster.close()


# ---------------------------------------------------------------------------
# summary table
# ---------------------------------------------------------------------------

def _columns(rows: list[dict]) -> list[str]:
    fn = []
    for r in rows:
        for key in FN_KEYS:
            for k in (r.get("parameters") or {}).get(key, {}):
                if f"{key}[{k}]" not in fn:
                    fn.append(f"{key}[{k}]")
    params = [p for p in PARAMS if any(p in (r.get("parameters") or {}) for r in rows)]
    return params + fn


def _split(col: str):
    """("fn_m", "y^3") for "fn_m[y^3]" (or "fn"), (None, col) for a plain parameter."""
    for key in FN_KEYS:
        if col.startswith(f"{key}["):
            return key, col[len(key) + 1:-1]
    return None, col


def _value(row: dict, col: str):
    p = row.get("parameters") or {}
    key, name = _split(col)
    return (p.get(key) or {}).get(name) if key else p.get(col)


def _interval(row: dict, col: str):
    iv = row.get("intervals") or {}
    key, name = _split(col)
    return (iv.get(key) or {}).get(name) if key else iv.get(col)


@contextlib.contextmanager
def _quiet_logs(name: str):
    """Only errors from logger ``name`` and its children inside."""
    log = logging.getLogger(name)
    level = log.level
    log.setLevel(logging.ERROR)
    try:
        yield
    finally:
        log.setLevel(level)


def write_csv(rows: list[dict], path: str | Path) -> Path:
    """One line per run: run, status, nrmse, each parameter with its interval, reason, notes."""
    path = Path(path)
    cols = _columns(rows)
    header = ["run", "status", "validation_stage", "nrmse"]
    for c in cols:
        header += [c, f"{c}_low", f"{c}_high"]
    header += ["written", "group", "seconds", "reason", "notes", "verdict", "verdict_text"]
    with path.open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(header)
        for r in rows:
            line = [r["run"], r["status"], r.get("validation_stage") or "", _fmt_csv(r.get("nrmse"))]
            for c in cols:
                iv = _interval(r, c) or [None, None]
                line += [_fmt_csv(_value(r, c)), _fmt_csv(iv[0]), _fmt_csv(iv[1])]
            line += [r.get("written", False), r.get("group", ""), f"{r.get('seconds', 0.0):.2f}", r.get("reason", ""),
                     "; ".join(r.get("notes", [])), r.get("verdict", ""), r.get("verdict_text", "")]
            w.writerow(line)
    return path


def _fmt_csv(v) -> str:
    return "" if v is None else repr(float(v))


def format_table(rows: list[dict]) -> str:
    """The summary printed for a person: one line per run, parameters to 4 significant digits."""
    cols = _columns(rows)
    header = ["run", "status", "nrmse", "verdict"] + cols
    lines = [header]
    for r in rows:
        shown = "" if r["status"] == "failed" else nrmse_text(r.get("nrmse"))
        line = [Path(r["run"]).name, r["status"], shown, r.get("verdict", "")]
        line += ["" if _value(r, c) is None else f"{_value(r, c):.4g}" for c in cols]
        lines.append(line)
    widths = [max(len(str(l[i])) for l in lines) for i in range(len(header))]
    out = ["  ".join(str(v).ljust(w) for v, w in zip(l, widths)).rstrip() for l in lines]
    bad = [r for r in rows if r["status"] == "failed"]
    if bad:
        out.append("")
        out.append("failed runs:")
        out += [f"  {r['reason']}" if r["reason"].startswith(r["run"]) else f"  {r['run']}: {r['reason']}"
                for r in bad]
    verdicts = [(r["run"], r["verdict_text"]) for r in rows if r.get("verdict_text")]
    if verdicts:
        out.append("")
        out.append("verdicts:")
        out += [f"  {Path(p).name}: {v}" for p, v in verdicts]
    notes = [(r["run"], n) for r in rows for n in r.get("notes", [])]
    if notes:
        out.append("")
        out.append("notes:")
        out += [f"  {p}: {n}" for p, n in notes]
    return "\n".join(out)


def batch_settings_dict(s: BatchSettings) -> dict:
    return asdict(s)


def write_simulated_run(path: str | Path, excitation: str = "base", snr_db: float | None = 80.0, fs: float = 2000.0,
                        duration: float = 10.0, seed: int = 0, stages: tuple | None = None, overwrite: bool = False):
    """A ground-truth run (recon.testing.truth.sdof_run) written as a cleanly closed .h5 run file.

    ``stages`` limits which stages are written (e.g. to make a run that lacks one).
    Returns the true model. Used by the tests and the benches."""

    run, truth = sdof_run(excitation, snr_db=snr_db, fs=fs, duration=duration, seed=seed)
    with RunWriter(path, overwrite=overwrite, attrs={"excitation": excitation, "simulated": True, "seed": seed}) as w:
        for name, st in run.stages.items():
            if stages is not None and name not in stages:
                continue
            sw = w.begin_stage(name, fs=fs, excitation=excitation, settings={"snr_db": snr_db})
            sw.append(0, st.channels)
            sw.close()
    return truth

"""`shakerlab backbone`: frequency and damping against amplitude from a stage's ring-down
(recon.backbone), measured and, with ``--model``, as the model simulates the same stage."""
from __future__ import annotations

import json
import math

import numpy as np
from recon.welch import welch

from recon.backbone import free_decay_backbone
from recon.model import HystereticModel
from shakerlab.errors import UserFacingError
from shakerlab.jsonsafe import clean
from shakerlab.runfile.reader import load_run

N_BINS = 8


def default_stage(run) -> str:
    """The first validation stage (named validation*, as everywhere in recon), else the last stage."""
    return next((n for n in run.stages if n.startswith("validation")), list(run.stages)[-1])


def response_peak(stage) -> float:
    """The frequency [Hz] of the largest peak of the stage's response spectrum (Welch)."""
    y = stage.y - np.mean(stage.y)
    f, p = welch(y, fs=stage.fs, nperseg=min(y.size, max(256, int(8 * stage.fs))))
    p[f <= 0] = 0.0
    return float(f[int(np.argmax(p))])


def backbone_table(run, stage_name: str, mode_hz: float | None = None, t_from: float | None = None,
                   t_to: float | None = None, band: float = 0.25, model: HystereticModel | None = None,
                   n_bins: int = N_BINS) -> dict:
    """The backbone of ``stage_name`` in amplitude bins (times from the stage's start), with the
    model's from its simulation of the same stage when ``model`` is given."""
    st = run.stage(stage_name)
    if mode_hz is None:
        mode_hz = math.sqrt(model.K_m) / (2 * math.pi) if model is not None and model.K_m > 0 else response_peak(st)
    if not (isinstance(n_bins, int) and n_bins >= 1):
        raise UserFacingError(f"backbone: --bins must be a positive integer, got {n_bins!r}")
    t = st.t - st.t[0]
    measured = free_decay_backbone(t, st.y, mode_hz, t_from, t_to, band)
    a = measured.amplitude
    lo, hi = float(np.percentile(a, 2)), float(np.percentile(a, 99.5))
    if not (lo > 0 and hi > lo):
        raise UserFacingError(f"backbone: stage {stage_name!r} has no amplitude range to bin (envelope "
                              f"{lo:.3g}-{hi:.3g}); choose another stage or window")
    edges = np.geomspace(lo, hi * (1 + 1e-9), n_bins + 1)
    rows = measured.binned(edges)
    out = {"run": run.source, "stage": stage_name, "mode_hz": float(mode_hz), "band": band,
           "window_s": [float(measured.t[0]), float(measured.t[-1])], "bins": rows}
    if model is not None:
        _, ys = model.simulate_stage(st)
        if not np.all(np.isfinite(ys)):
            raise UserFacingError(f"backbone: the model's simulation of stage {stage_name!r} diverged")
        sim = free_decay_backbone(t, ys, mode_hz, t_from, t_to, band)
        for r, m in zip(rows, sim.binned(edges)):
            r["model_frequency_hz"], r["model_damping_ratio"] = m["frequency_hz"], m["damping_ratio"]
    return out


def _cell(v, scale=1.0, spec=".4f") -> str:
    return "-" if v is None else format(v * scale, spec)


def backbone_command(args) -> int:
    run = load_run(args.run)
    model = HystereticModel.load(args.model) if args.model else None
    out = backbone_table(run, args.stage or default_stage(run), args.mode_hz, args.t_from, args.t_to, args.band,
                         model, args.bins)
    if args.json:
        print(json.dumps(clean(out)))
        return 0
    print(f"{run.source}: stage {out['stage']}, mode near {out['mode_hz']:.4g} Hz, band +-{100 * out['band']:.0f} %, "
          f"{out['window_s'][0]:.3g}-{out['window_s'][1]:.3g} s")
    head = "amplitude            samples  frequency Hz  damping %"
    if model is not None:
        head += "  model Hz   model damping %"
    print(head)
    for r in out["bins"]:
        line = (f"{r['amplitude_low']:9.3g}-{r['amplitude_high']:<9.3g} {r['samples']:8d}  "
                f"{_cell(r['frequency_hz']):>12}  {_cell(r['damping_ratio'], 100, '.3f'):>9}")
        if model is not None:
            line += f"  {_cell(r['model_frequency_hz']):>8}  {_cell(r['model_damping_ratio'], 100, '.3f'):>15}"
        print(line)
    return 0

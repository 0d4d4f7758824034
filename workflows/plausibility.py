"""Plausibility of a run's amplitudes: warnings (never errors) for numbers no shaker rig produces.

Two checks, both ending in "units?":

- a displacement whose amplitude (peak distance from the channel's median) exceeds
  ``MAX_DISPLACEMENT_M``: a laboratory shaker's stroke is a few centimetres at most, so a larger
  value is almost always a channel recorded in mm (or um) read as metres;
- the response per unit drive of one stage against another's: the drive is the generator amplitude
  of the stage's recorded setpoints (V) when there are any, else the stage's input channel (x_base or
  force). One stage whose ratio is ``UNIT_RATIO`` times another's (a stage ~1000x larger than its
  drive predicts) was most likely recorded in other units. The drive amplitudes themselves are
  compared too (the same factor between two stages' inputs).

The linear step's sign check (negative damping or stiffness: base and tip swapped?) belongs to the
reconstruction: ``recon.steps.linear.plausibility_warnings``. :func:`warnings_for` gathers both.
"""
from __future__ import annotations

import numpy as np

from shakerlab.run_data import BASE, Run, Stage

MAX_DISPLACEMENT_M = 0.05
UNIT_RATIO = 300.0


def _amplitude(x: np.ndarray) -> float:
    x = np.asarray(x, float)
    x = x[np.isfinite(x)]
    return float(np.max(np.abs(x - np.median(x)))) if x.size else 0.0


def _rms(x: np.ndarray) -> float:
    x = np.asarray(x, float)
    x = x[np.isfinite(x)]
    return float(np.sqrt(np.mean((x - np.mean(x)) ** 2))) if x.size else 0.0


def _drive(st: Stage) -> tuple[str, float]:
    """("V", generator amplitude) from the recorded setpoints, else (input channel name, its rms)."""
    vpp = [s.get("amplitude_vpp", 0.0) for s in (st.settings or {}).get("steps", []) or []]
    vpp = [v for v in vpp if np.isfinite(v) and v > 0]
    if vpp:
        return "V", float(max(vpp))
    ch = "x_base" if st.excitation == BASE else "force"
    return ch, _rms(st.channels[ch])


def run_warnings(run: Run) -> list[str]:
    out = []
    for name, st in run.stages.items():
        for ch in ("x_base", "x_tip", "x"):
            if ch in st.channels:
                a = _amplitude(st.channels[ch])
                if a > MAX_DISPLACEMENT_M:
                    out.append(f"stage {name!r}: {ch} moves by {a:.4g} m, beyond any shaker's stroke "
                               f"({MAX_DISPLACEMENT_M:g} m): units? (displacements are in metres)")
    gains: dict[str, tuple[str, float, float]] = {}
    for name, st in run.stages.items():
        kind, d = _drive(st)
        r = _rms(st.channels["x_tip" if st.excitation == BASE else "x"])
        if d > 0 and r > 0:
            gains[name] = (kind, d, r / d)
    names = list(gains)
    for i, a in enumerate(names):
        for b in names[i + 1:]:
            ka, da, ga = gains[a]
            kb, db, gb = gains[b]
            if ka != kb:
                continue
            for what, va, vb in (("response per unit drive", ga, gb), (f"drive amplitude ({ka})", da, db)):
                big, small, vbig, vsmall = (a, b, va, vb) if va >= vb else (b, a, vb, va)
                if vbig > UNIT_RATIO * vsmall:
                    out.append(f"stage {big!r}: {what} is {vbig / vsmall:.3g}x that of stage {small!r}: units? "
                               f"(one stage in mm, the others in m?)")
    return out


def warnings_for(run: Run, result=None) -> list[str]:
    """The run's amplitude warnings, plus the reconstruction's linear-step warnings when given."""
    out = run_warnings(run)
    if result is not None:
        out += [w for w in getattr(result.linear, "warnings", []) if w not in out]
    return out

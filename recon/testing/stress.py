"""The recordings of the stress benches, each reproducible from its index alone.

Diagnosis stress (bench/diagnose.py --stress): recording i is a random TMP-like system
(f_n 5-60 Hz, y^2, y^3 and Bouc-Wen each on or off, (gamma, delta) of either sign), a random
protocol (paper, rig, sweep, multisine), fs log-uniform 1-10 kHz, SNR uniform 40-80 dB (half of
them quantised), one concealed effect taken in turn from "none" (twice per cycle) and every catalog
id the generator implements, at a strength uniform in 0.3-1.5 of its nominal scale
(:func:`draw`, :func:`recording`).

Reconstruction stress (bench/recon_accuracy.py --stress): seed s is a random system
with Bouc-Wen hysteresis, a protocol and a sample rate (:func:`stress_system`).

Both draw from the independent generator (recon/testing/independent.py), which shares no code
with the estimator.
"""
from __future__ import annotations

import math

import numpy as np

from recon.diagnosis.catalog import CATALOG
from recon.testing import independent as ind


def effect_cycle() -> list[str]:
    ids = [e for e in ind.PHYSICAL_EFFECTS + ind.STRUCTURAL_EFFECTS if e in CATALOG]
    return ["none", "none"] + ids


FIRST_MODE_DRIVE_ROW = 289


def draw(i: int) -> dict:
    """The recording parameters of stress recording i."""
    rng = np.random.default_rng([i, 13])
    cyc = effect_cycle()
    return {"index": i, "system": ind.random_system(rng, hysteresis=None),
            "protocol": str(rng.choice(ind.PROTOCOLS)),
            "fs": float(np.round(math.exp(rng.uniform(math.log(1000.0), math.log(10000.0))))),
            "snr": float(np.round(rng.uniform(40.0, 80.0), 1)),
            "quantisation": float(rng.uniform(0.2, 1.0)) if rng.random() < 0.5 else None,
            "effect": cyc[i % len(cyc)], "strength": float(rng.uniform(0.3, 1.5)),
            # from row FIRST_MODE_DRIVE_ROW on, half the higher modes ride on the tip (driven by its
            # absolute acceleration, as a mount resonance is), drawn apart so earlier rows stay as they were
            **({"mode_drive": float(np.random.default_rng([i, 29]).random() < 0.5)}
               if i >= FIRST_MODE_DRIVE_ROW and cyc[i % len(cyc)] == "higher_mode" else {})}


def recording(d: dict) -> dict:
    """The noisy recording of the draw ``d`` (:func:`draw`), as the generator returns it."""
    i = d["index"]
    rec = ind.simulate(d["system"], d["protocol"], d["fs"], d["effect"], d["strength"], seed=i,
                       mode_drive=d.get("mode_drive", 0.0))
    return ind.add_noise(rec, d["snr"], i, d["quantisation"])


def stress_system(seed: int, protocols=("paper", "rig")) -> tuple[dict, str, float]:
    """System, protocol and sample rate of the reconstruction stress bench's ``seed`` (reproducible)."""
    rng = np.random.default_rng([seed, 18])
    system = ind.random_system(rng, hysteresis=True)
    fs = float(np.round(math.exp(rng.uniform(math.log(1000.0), math.log(10000.0)))))
    return system, protocols[seed % len(protocols)], fs

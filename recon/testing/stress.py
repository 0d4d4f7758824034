"""The recordings of the stress benches, each reproducible from its index alone.

Diagnosis stress (bench/diagnose.py --stress): recording i is a random TMP-like system
(f_n 5-60 Hz, y^2, y^3 and Bouc-Wen each on or off, (gamma, delta) of either sign), a random
protocol (paper, rig, sweep, multisine), fs log-uniform 1-10 kHz, SNR uniform 40-80 dB (half of
them quantised), one concealed effect taken in turn from "none" (twice per cycle) and every catalog
id the generator implements, at a strength uniform in 0.3-1.5 of its nominal scale
(:func:`draw`, :func:`recording`).

Apart from that block (reported apart: :func:`corner_draw`, :func:`pair_draw`,
:func:`weak_linear_draw`): issue 76's corner, two effects concealed together, and a linear stage
recorded at 0-10 dB SNR.

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


# The corner of issue 76 (a system outside the random draws' reach): a Bouc-Wen law with negative
# delta beside a hardening cubic and y^2 y' damping, f_n near 24 Hz, sampled at 5 kHz with a
# sensor noise of 0.1-0.5 um on both channels, the paper's one-tone stages with the validation
# stage above the resonance, a second mode at 3.2-4 f_n. Its effects in turn:
CORNER_EFFECTS = ("none", "none", "coulomb_friction", "quadratic_damping", "higher_mode", "sensor_scale",
                  "channel_delay", "contact_stiffness", "parameter_drift")
CORNER_FS = 5000.0
CORNER_MODE_RATIO = (3.2, 4.0)


def corner_draw(i: int) -> dict:
    """The recording parameters of corner recording i (independent of :func:`draw`'s rows)."""
    rng = np.random.default_rng([i, 76])
    return {"index": i, "corner": "issue76", "system": ind.corner_system(rng), "protocol": "paper_above",
            "fs": CORNER_FS, "snr": None, "noise_m": float(rng.uniform(0.1e-6, 0.5e-6)), "quantisation": None,
            "effect": CORNER_EFFECTS[i % len(CORNER_EFFECTS)], "strength": float(rng.uniform(0.3, 1.5)),
            "mode_drive": float(rng.random() < 0.5)}


def corner_recording(d: dict) -> dict:
    """The noisy recording of the corner draw ``d`` (:func:`corner_draw`)."""
    i = d["index"]
    rec = ind.simulate(d["system"], d["protocol"], d["fs"], d["effect"], d["strength"], seed=i,
                       mode_drive=d["mode_drive"] if d["effect"] == "higher_mode" else 0.0,
                       mode_ratio=CORNER_MODE_RATIO)
    return ind.add_noise(rec, None, i, None, noise_std=d["noise_m"])


# Two effects concealed together (issue 74): pairs of physical effects a rig can have at once, in turn.
# The first of a pair is the generator's ``effect`` (a contact must be first: its gap is calibrated on
# the motion; a second mode too, so that its drive can ride on the tip), the second its ``also``.
PAIRS = (("coulomb_friction", "parameter_drift"),     # a dry joint warming up
         ("quadratic_damping", "channel_delay"),      # air drag, a late tip channel
         ("contact_stiffness", "sensor_scale"),       # an end stop, a miscalibrated tip sensor
         ("higher_mode", "coulomb_friction"),         # a fixture resonance, a dry joint
         ("parameter_drift", "sensor_scale"),         # a specimen warming up, a miscalibrated sensor
         ("contact_stiffness", "offset"),             # an end stop, a static preload
         ("quadratic_damping", "coulomb_friction"),   # two dissipations at once
         ("higher_mode", "channel_delay"))            # a fixture resonance, a late tip channel
PAIR_STRENGTH = (0.5, 1.5)
PAIR_SNR = (50.0, 80.0)


def pair_draw(i: int) -> dict:
    """The recording parameters of pair recording i (independent of :func:`draw`'s rows): a random
    system, protocol and fs as :func:`draw` has them, SNR uniform in PAIR_SNR (half of them quantised),
    the pair ``PAIRS[i % len(PAIRS)]`` concealed together, each at a strength uniform in PAIR_STRENGTH
    of its nominal scale; a second mode rides on the tip on half of its rows."""
    rng = np.random.default_rng([i, 74, 2])
    first, second = PAIRS[i % len(PAIRS)]
    return {"index": i, "block": "pairs", "system": ind.random_system(rng, hysteresis=None),
            "protocol": str(rng.choice(ind.PROTOCOLS)),
            "fs": float(np.round(math.exp(rng.uniform(math.log(1000.0), math.log(10000.0))))),
            "snr": float(np.round(rng.uniform(*PAIR_SNR), 1)),
            "quantisation": float(rng.uniform(0.2, 1.0)) if rng.random() < 0.5 else None,
            "effect": first, "strength": float(rng.uniform(*PAIR_STRENGTH)),
            "also": [[second, float(rng.uniform(*PAIR_STRENGTH))]],
            "mode_drive": float(rng.random() < 0.5) if first == "higher_mode" else 0.0}


def pair_recording(d: dict) -> dict:
    """The noisy recording of the pair draw ``d`` (:func:`pair_draw`)."""
    i = d["index"]
    rec = ind.simulate(d["system"], d["protocol"], d["fs"], d["effect"], d["strength"], seed=i,
                       mode_drive=d["mode_drive"], also=tuple((e, s) for e, s in d["also"]))
    return ind.add_noise(rec, d["snr"], i, d["quantisation"])


def concealed_effects(d: dict) -> list[str]:
    """The catalog ids a draw conceals (none for a clean one): the generator's effect names are the
    catalog's ids."""
    return [e for e in [d["effect"]] + [a[0] for a in d.get("also", [])] if e != "none"]


# A linear stage recorded far noisier than the others (issue 74, "a weak linear stage is not the end"):
# the random rows of draw(), their effects in turn, with the linear stage at 0-10 dB and the others at
# 40-80 dB.
WEAK_LINEAR_SNR = (0.0, 10.0)
WEAK_LINEAR_OTHER_SNR = (40.0, 80.0)


def weak_linear_draw(i: int) -> dict:
    """The recording parameters of weak-linear recording i (independent of :func:`draw`'s rows):
    system, protocol, fs, quantisation, effect (in :func:`effect_cycle`'s turn) and strength as
    :func:`draw` has them; ``snr`` (every stage but the linear one) uniform in WEAK_LINEAR_OTHER_SNR,
    ``linear_snr`` (the linear stage) uniform in WEAK_LINEAR_SNR."""
    rng = np.random.default_rng([i, 74, 1])
    cyc = effect_cycle()
    return {"index": i, "block": "weak_linear", "system": ind.random_system(rng, hysteresis=None),
            "protocol": str(rng.choice(ind.PROTOCOLS)),
            "fs": float(np.round(math.exp(rng.uniform(math.log(1000.0), math.log(10000.0))))),
            "snr": float(np.round(rng.uniform(*WEAK_LINEAR_OTHER_SNR), 1)),
            "linear_snr": float(np.round(rng.uniform(*WEAK_LINEAR_SNR), 1)),
            "quantisation": float(rng.uniform(0.2, 1.0)) if rng.random() < 0.5 else None,
            "effect": cyc[i % len(cyc)], "strength": float(rng.uniform(0.3, 1.5)),
            "mode_drive": float(rng.random() < 0.5) if cyc[i % len(cyc)] == "higher_mode" else 0.0}


def weak_linear_recording(d: dict) -> dict:
    """The noisy recording of the weak-linear draw ``d`` (:func:`weak_linear_draw`)."""
    i = d["index"]
    rec = ind.simulate(d["system"], d["protocol"], d["fs"], d["effect"], d["strength"], seed=i,
                       mode_drive=d["mode_drive"])
    return ind.add_noise(rec, d["snr"], i, d["quantisation"], stage_snr_db={"linear": d["linear_snr"]})


def stress_system(seed: int, protocols=("paper", "rig")) -> tuple[dict, str, float]:
    """System, protocol and sample rate of the reconstruction stress bench's ``seed`` (reproducible)."""
    rng = np.random.default_rng([seed, 18])
    system = ind.random_system(rng, hysteresis=True)
    fs = float(np.round(math.exp(rng.uniform(math.log(1000.0), math.log(10000.0)))))
    return system, protocols[seed % len(protocols)], fs

"""exciter_distortion: the exciter turns its drive into force with an even-order distortion and a
low-frequency roll-off (force excitation from a recorded drive)."""
import math

from recon.diagnosis.candidates.base import Candidate, start_model
from shakerlab.run_data import BASE


def starts(base, ctx):
    # the drive's roll-off starts inside its bound (0.1 Hz), the distortion at 0 (recon.exciter)
    m = start_model(base, {}, "exciter_distortion")
    m.baseline.drive_u2, m.baseline.drive_hp = 0.0, 2 * math.pi * 0.1
    return [(m, ["drive_u2", "drive_hp"], {"drive_u2": 0.01 / ctx["u_rms"], "drive_hp": 2 * math.pi * 0.5},
             {"drive_hp": (0.0, 2 * math.pi * 0.5 * ctx["f_res"])})]


CANDIDATE = Candidate(
    "exciter_distortion",
    "the input is the exciter's drive (an amplifier voltage), and the exciter does not turn it into "
    "force in proportion: an even-order distortion (u^2) and a low-frequency roll-off",
    "model change: the force is HP(u + u2 u^2), a first-order high-pass of corner hp",
    "the drive transformed (recon.exciter), then the SDOF (force excitation only)",
    ("drive_u2", "drive_hp"), starts, lambda b, c: b.excitation != BASE and not b.has_drive,
    amplitude_dependent=True)

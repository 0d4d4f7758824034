"""The catalog's candidates, one module each (what a candidate holds: base.py; how to add one:
docs/diagnosis.md, "Adding a candidate"). The order below is the order they are fitted and
listed in."""
from recon.diagnosis.candidates import (amplitude_damping, channel_delay, contact_stiffness, coulomb_friction,
                                        cubic_stiffness, exciter_distortion, higher_mode, hysteresis, offset,
                                        parameter_drift, quadratic_damping, quadratic_stiffness, sensor_scale)
from recon.diagnosis.candidates.base import Candidate

REGISTERED: tuple[Candidate, ...] = tuple(m.CANDIDATE for m in (
    cubic_stiffness, quadratic_stiffness, quadratic_damping, coulomb_friction, contact_stiffness, channel_delay,
    sensor_scale, parameter_drift, higher_mode, offset, amplitude_damping, exciter_distortion, hysteresis))

__all__ = ["Candidate", "REGISTERED"]

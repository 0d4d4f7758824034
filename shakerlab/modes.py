"""The kind of test a run records, kept in the run file's attributes (``mode``).

- ``structure`` (no attribute: every run recorded before modes existed): a structure on the
  shaker or under a force, the model is the equation of motion (recon.estimator);
- ``constitutive``: a component test, the displacement imposed and the force measured, the
  model is the force law (recon.constitutive, docs/constitutive.md).
"""
from __future__ import annotations

MODE_ATTR = "mode"
STRUCTURE = "structure"
CONSTITUTIVE = "constitutive"
MODES = (STRUCTURE, CONSTITUTIVE)
# the optional channels of a constitutive stage besides x and force
VELOCITY_CHANNEL = "velocity"      # a measured velocity [m/s] (CSV column v)
COMMAND_CHANNEL = "command"        # an extra input, e.g. an MR damper's coil voltage (CSV column cmd)


def run_mode(run) -> str:
    """The mode of a Run (or of a run file's attribute dict)."""
    attrs = run if isinstance(run, dict) else getattr(run, "attrs", {}) or {}
    return str(attrs.get(MODE_ATTR, STRUCTURE))

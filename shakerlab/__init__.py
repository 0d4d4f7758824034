"""shakerlab: shaker-rig experiments on hysteretic structures.

The distribution ships five top-level packages:

- ``drivers``      instrument drivers (SCPI generator, Modbus amplifier, laser sensors)
- ``sim_backend``  a simulated TMP-origami rig that speaks the instruments' protocols
- ``rig``          the supervised incremental-excitation protocol and its runner
- ``recon``        reconstruction of hysteretic governing equations from recordings
- ``shakerlab``    the command line and the recording format shared by rig and recon
"""

__version__ = "0.1.0"

"""Reconstruction of hysteretic governing equations from recorded motion. Never imports rig or drivers."""

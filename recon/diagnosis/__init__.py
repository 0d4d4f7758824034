"""Mismatch diagnosis: locate where a model and a recording disagree, name the missing physics
from a catalog, fit the augmented model and show the fit improve (see docs/diagnosis.md)."""

"""The catalog of candidate missing physics: the registered candidates by id.

Each candidate is one module of recon/diagnosis/candidates/ (what it holds: candidates/base.py);
the catalog is their list, in the order they are fitted. ``CATALOG[id]`` is a
:class:`~recon.diagnosis.candidates.base.Candidate`; :func:`describe` gives the plain records
the docs and ``--json`` consumers read; :data:`SIGNATURES` and :data:`AMPLITUDE_DEPENDENT` are
the candidates' own declarations gathered.
"""
from __future__ import annotations

from recon.diagnosis.candidates import REGISTERED
from recon.diagnosis.candidates.base import Candidate

CATALOG: dict[str, Candidate] = {c.id: c for c in REGISTERED}

# which located findings support which candidate (evidence, not the decision)
SIGNATURES: dict[str, tuple] = {c.id: c.signature for c in REGISTERED if c.signature}
# effects whose size changes with amplitude at one frequency (recon.diagnosis.ambiguity)
AMPLITUDE_DEPENDENT: frozenset = frozenset(c.id for c in REGISTERED if c.amplitude_dependent)


def describe() -> list[dict]:
    """The catalog as plain records (for docs and --json consumers)."""
    return [{"id": c.id, "explanation": c.explanation, "adds": c.adds, "simulated": c.simulated}
            for c in CATALOG.values()]

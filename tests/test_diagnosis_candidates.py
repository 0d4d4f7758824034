"""One contract over every registered candidate (recon/diagnosis/candidates/): what a candidate
module must hold, and that each one, concealed in a synthetic truth, is named with its size."""
import math

import numpy as np
import pytest

from recon.diagnosis.augmented import EXTRAS, AugmentedModel
from recon.diagnosis.candidates import REGISTERED
from recon.diagnosis.candidates.base import Candidate
from recon.diagnosis.catalog import AMPLITUDE_DEPENDENT, CATALOG, SIGNATURES
from recon.diagnosis.diagnose import diagnose
from recon.model import PARAMETER_NAMES
from recon.output_error.problem import get_parameter, set_parameter
from recon.simulation.rk4 import P_NAMES
from recon.testing.concealed import concealed_run, effect_truth
from shakerlab.run_data import FORCE

IDS = [c.id for c in REGISTERED]
# the kinds of finding locate.py can report (the evidence a candidate's signature may name)
FINDING_KINDS = {"time_segment", "time_trend", "frequency_harmonic", "frequency_band_at_input",
                 "frequency_resonance", "channel", "state_cluster", "state_near_zero_velocity",
                 "state_beyond_displacement", "correlation_tests"}
MODEL_KEYS = set(PARAMETER_NAMES) | {"drive_u2", "drive_hp", "inv_m"}


def known_key(key: str) -> bool:
    if key.startswith("fn:"):
        return bool(key[3:])
    if key.startswith("x:"):
        return key[2:] in EXTRAS
    return key in MODEL_KEYS


def kernel_slots_moved(m: AugmentedModel, key: str) -> set:
    """The slots of the simulation kernel's parameter vector that moving ``key`` of ``m`` changes."""
    value = get_parameter(m, key)
    moved = m.copy()
    set_parameter(moved, key, -value if value != 0.0 else 1.0)
    before, after = m.kernel_vector(), moved.kernel_vector()
    return {name for name, a, b in zip(P_NAMES, before, after) if a != b}


@pytest.fixture(scope="module")
def context():
    """A short record's baseline and locate context (what every candidate's starts read)."""
    run, _, _, baseline = concealed_run(None, duration=1.5, seed=3)
    d = diagnose(run, baseline, candidates=["channel_delay"])
    return baseline, d.context


def test_the_catalog_is_the_registered_candidates_in_order():
    assert list(CATALOG) == IDS and len(set(IDS)) == len(IDS)
    assert all(isinstance(c, Candidate) for c in REGISTERED)
    assert SIGNATURES == {c.id: c.signature for c in REGISTERED if c.signature}
    assert AMPLITUDE_DEPENDENT == {c.id for c in REGISTERED if c.amplitude_dependent}


@pytest.mark.parametrize("cid", IDS)
def test_a_candidate_declares_what_it_adds_and_how_it_is_fitted(cid, context):
    cand = CATALOG[cid]
    assert cand.explanation and cand.adds and cand.simulated
    assert cand.parameters and all(known_key(k) for k in cand.parameters), cand.parameters
    assert set(cand.signature) <= FINDING_KINDS, cand.signature
    # its contribution to the simulation kernel: slots of its parameter vector, by name
    assert set(cand.kernel) <= set(P_NAMES) and len(set(cand.kernel)) == len(cand.kernel), cand.kernel
    baseline, ctx = context
    base = baseline
    if not cand.applies(base, ctx):
        # a baseline that lacks the candidate: the one its own recipe makes, or a force-excited
        # baseline without an exciter model (the exciter's distortion)
        base = (effect_truth(cid, 1.0)[2] if cand.conceal is not None
                else effect_truth(None, 1.0, excitation=FORCE)[2])
        ctx = {**ctx, "u_rms": 1.0, "f_res": 15.0}
    assert cand.applies(base, ctx), "no baseline it applies to"
    starts = cand.starts(base, ctx)
    assert starts, "no start"
    for m, keys, scales, bounds in starts:
        assert isinstance(m, AugmentedModel) and cid in m.added
        assert keys and all(known_key(k) for k in keys), keys
        assert all(k in keys for k in scales) and all(v > 0 and math.isfinite(v) for v in scales.values())
        # the kernel slots its parameters (free, reported, or fitted once per value) set are declared
        moved = set().union(*(kernel_slots_moved(m, k) for k in {*keys, *cand.parameters,
                                                                 *([f"x:{cand.fit_each}"] if cand.fit_each else [])}))
        assert moved <= set(cand.kernel), (sorted(moved), cand.kernel)
        for k, (lo, hi) in bounds.items():
            assert k in keys and lo < hi and lo <= get_parameter(m, k) <= hi, (k, lo, hi, get_parameter(m, k))
    if cand.admissible_starts is not None:
        assert cand.admissible_starts(base, ctx)


@pytest.mark.parametrize("cid", IDS)
def test_a_candidate_can_be_concealed_or_says_why_not(cid):
    cand = CATALOG[cid]
    if cand.conceal is None:
        # only the exciter's distortion, which needs a recorded drive rather than a force
        assert cid == "exciter_distortion"
        return
    truth, extras, baseline = effect_truth(cid, 1.0)
    assert set(extras) <= set(EXTRAS)
    assert truth.to_dict() != baseline.to_dict() or extras, "concealing changed nothing"


# the size each concealed effect is checked by (its first parameter), where the first parameter is
# not a size the truth states (the hysteresis loop: alpha)
SIZE_OF = {"hysteresis": "alpha_m"}


@pytest.mark.slow
@pytest.mark.parametrize("cid", [c.id for c in REGISTERED if c.conceal is not None])
def test_every_candidate_concealed_in_a_synthetic_truth_is_named_with_its_size(cid):
    """The contract on ground truth: concealed at twice the strength that raises the baseline's
    error by a few per cent, fitted alone against the baseline without it, the candidate is named
    and its size is the truth's within 20 %."""
    run, truth, extras, baseline = concealed_run(cid, strength=2.0, seed=IDS.index(cid), duration=3.0)
    d = diagnose(run, baseline, candidates=[cid])
    assert [m["id"] for m in d.missing] == [cid], d.to_dict()["candidates_tested"]
    key = SIZE_OF.get(cid, CATALOG[cid].parameters[0])
    true = AugmentedModel(truth, extras).get(key[2:]) if key.startswith("x:") else get_parameter(truth, key)
    got = get_parameter(d.best, key)
    assert np.isfinite(got) and abs(got / true - 1) < 0.2, (key, got, true)

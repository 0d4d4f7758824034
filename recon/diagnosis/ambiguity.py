"""When two candidates explain the held-out mismatch about equally well: say so, and propose the
stage that would separate them, as a protocol TOML that `shakerlab acquire --protocol` reads
(docs/protocol.md; the file is the shipped default protocol plus separating validation stages).

Two significant candidates A (ranked first) and B are *ambiguous* when B does not add on top of A
(the forward step did not keep it) and A is not significantly better than B on the held-out
samples: n_eff ln(MSE_B / MSE_A) < bic_margin, or A's lead over B is less than model_error_share
(DiagnosisSettings) of the excess A itself leaves over the noise floor:
MSE_B - MSE_A < model_error_share (MSE_A - noise).
The BIC margin counts the held-out residual as noise; where the first candidate leaves much of the
mismatch unexplained, the residual is mostly model error, and a lead small beside it says which fit
copes better with that error, not which effect is there (for example, under quadratic damping a
stiffness drift or an amplitude-dependent damping can explain a few per cent more of the excess
than the true term while both fits stay far from the truth's figure).
"""
from __future__ import annotations

import math

from recon.diagnosis.catalog import AMPLITUDE_DEPENDENT
from recon.diagnosis.settings import DEFAULTS, DiagnosisSettings

# what separates a pair: effects whose share of the response changes differently with amplitude
# (each candidate declares it: Candidate.amplitude_dependent) are told apart by a second amplitude
# at the same frequency; effects that trade off at one frequency (a scale error against a
# stiffness, a delay against damping) by a frequency step

PROTOCOL_HEAD = """# shakerlab protocol proposed by `shakerlab diagnose` to separate {a} from {b}
# (the shipped default protocol, plus the separating validation stage(s) at the end).
# Every field is documented in docs/protocol.md; check the amplitudes against your rig first.

[run]
settle_s = 1.0

[linear]
frequency_hz = 8.0
amplitude_vpp = 0.4
duration_s = 4.0

[resonance_search]
enabled = true
method = "stepped"
start_hz = 6.0
stop_hz = 30.0
steps = 12
refine_steps = 5
amplitude_vpp = 0.05
settle_s = 1.0
measure_s = 0.5

[nonlinear]
frequency_factor = 0.88
start_vpp = 0.25
step_factor = 1.5
max_vpp = 5.5
dwell_s = 1.5
analysis_s = 0.75
hold_s = 4.0
thd_threshold = 0.012
gain_change_threshold = 0.45
loss_change_threshold = 2.0

[[validation]]
frequency_factor = 0.7
amplitude_fraction = 1.0
duration_s = 4.0
"""

AMPLITUDE_STAGE = """
[[validation]]              # separating: a second amplitude at the nonlinear stage's frequency
name = "validation_amplitude"
frequency_factor = 0.88
amplitude_fraction = 0.4
duration_s = 6.0
"""

FREQUENCY_STAGE = """
[[validation]]              # separating: a frequency step above the resonance, same level
name = "validation_frequency"
frequency_factor = 1.3
amplitude_fraction = 1.0
duration_s = 6.0
"""

def ambiguous_pair(ranked: list[dict], kept: set, mse: dict, bic_margin: float,
                   noise_mse: float | None = None, settings: DiagnosisSettings = DEFAULTS) -> list[str] | None:
    """The first pair (ranked[0], B) that the held-out data cannot tell apart, or None.

    ``ranked``: significant candidates, best first, with their ``n_eff``; ``kept``: ids the forward
    step kept (they add on top of the first, so they are not rivals); ``mse``: held-out MSE by id;
    ``noise_mse``: the held-out noise floor's mean square (None: the BIC margin alone);
    ``settings.model_error_share``: the share of the first's excess over the noise within which the
    runner-up's MSE makes the pair ambiguous."""
    if len(ranked) < 2:
        return None
    a = ranked[0]
    for t in ranked[1:]:
        if t["id"] in kept:
            continue
        ma, mb = mse[a["id"]], mse[t["id"]]
        if not (ma > 0 and math.isfinite(mb)):
            continue
        if a["n_eff"] * math.log(mb / ma) < bic_margin:
            return [a["id"], t["id"]]
        if noise_mse is not None and ma > noise_mse and mb - ma < settings.model_error_share * (ma - noise_mse):
            return [a["id"], t["id"]]
    return None


def separating_stage(pair: list[str]) -> dict:
    """The proposed separating stage(s) for ``pair``: the reason and the protocol TOML."""
    a, b = pair
    amp = a in AMPLITUDE_DEPENDENT or b in AMPLITUDE_DEPENDENT
    freq = not (a in AMPLITUDE_DEPENDENT and b in AMPLITUDE_DEPENDENT)
    stages, why = [], []
    if amp:
        stages.append(AMPLITUDE_STAGE)
        why.append("a second amplitude at the same frequency (the two effects scale differently with amplitude)")
    if freq:
        stages.append(FREQUENCY_STAGE)
        why.append("a frequency step at the same level (the two effects trade off at one frequency only)")
    return {"ids": [a, b], "stages": [s.split('name = "')[1].split('"')[0] for s in stages],
            "reason": "; ".join(why), "protocol_toml": PROTOCOL_HEAD.format(a=a, b=b) + "".join(stages)}

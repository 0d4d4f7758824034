"""When reconstruct fits a constant input offset on its own (``ReconSettings(input_offset="auto")``).

Under base excitation the model's input u = -x_base'' has no DC: a second derivative of a bounded
motion averages to zero over a record. The relative motion y of a stage whose amplitude is small
enough to stay nearly elastic (the linear stage) then has no DC either, unless something the
excitation cannot make holds it off centre: a constant force on the specimen (its weight on a
tilted rig, a preload) or a sensor's DC offset. Either is a constant term of the equation of
motion (``fn`` of degree 0, or the model's input offset b). Left out, the regression spends its
even terms on it: on independent-generator recording #9 of the diagnosis stress (multisine,
50.5 dB, a constant force) the linear stage's mean was 9.4 times its rms motion, and the model
came out with 15 terms and k at 7 % of the truth; with the offset fitted it is exact to 1.4 %.

Rule: on when the linear stage's |mean(y)| exceeds ``dc_share`` (recon.estimator.tuning) of its rms
motion about the mean.
Measured on the independent generator: 60 records without an offset (37 of the diagnosis stress,
the first 20 recon stress draws at 60 dB, 3 of the own generator) reach at most 0.022; the three
offset records of the diagnosis stress have 5.1, 9.4 and 10.6. Force excitation: off (a recorded force
may carry a DC the static stiffness explains; set ``input_offset=True`` to fit one).
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np

from shakerlab.run_data import BASE, Run


def resolve_input_offset(run: Run, settings):
    """(settings with input_offset True/False, the decision's figures or None when it was given)."""
    if settings.input_offset != "auto":
        return settings, None
    name = settings.linear_stage
    if name not in run.stages:
        return replace(settings, input_offset=False), {"on": False, "reason": f"no stage {name!r}"}
    st = run.stage(name)
    if st.excitation != BASE:
        return replace(settings, input_offset=False), {
            "on": False, "reason": "force excitation: a DC of the response may be the recorded force's own"}
    y = np.asarray(st.y, float)
    mean = float(np.mean(y))
    rms = float(np.std(y))
    share = abs(mean) / rms if rms > 0 else 0.0
    limit = settings.tuning.dc_share
    on = bool(share > limit)
    reason = f"the {name} stage's mean relative motion is {share:.3g} times its rms motion "
    reason += f"(> {limit:g}): a DC the base excitation cannot make" if on else f"(<= {limit:g})"
    return replace(settings, input_offset=on), {"on": on, "stage": name, "dc_share": share,
                                                "threshold": limit, "reason": reason}

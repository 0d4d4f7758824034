"""When reconstruct fits a constant input offset on its own (``ReconSettings(input_offset="auto")``).

Under base excitation the model's input u = -x_base'' has no DC: a second derivative of a bounded
motion averages to zero over a record. The relative motion y of a stage whose amplitude is small
enough to stay nearly elastic (the linear stage) then has no DC either, unless something the
excitation cannot make holds it off centre: a constant force on the specimen (its weight on a
tilted rig, a preload) or a sensor's DC offset. Either is a constant term of the equation of
motion (``fn`` of degree 0, or the model's input offset b). Left out, the regression spends its
even terms on it, and a record whose linear stage sits off centre by several times its motion
comes out with a dozen terms and a stiffness far from the truth; with the offset fitted it is
exact to about 1 %.

Rule: on when the linear stage's |mean(y)| exceeds ``dc_share`` (recon.estimator.tuning) of its rms
motion about the mean. A record without an offset has a mean of a few hundredths of its motion at
most (the ends of a stage that does not return exactly to rest); an offset of the size that spoils
the regression is several times the motion, so the threshold sits far from both (the measured
figures: docs/method.md). Force excitation: off (a recorded force
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

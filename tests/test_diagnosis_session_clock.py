"""A slow change runs on the session's clock: a rig run file gives each stage's start on it (t0)."""
import pytest

from recon.diagnosis import rank
from recon.diagnosis.diagnose import diagnose
from recon.diagnosis.augmented import AugmentedModel
from recon.testing.concealed import concealed_run
from shakerlab.run_data import Run, Stage


def as_rig_file(run: Run) -> Run:
    """The run as the rig's run file gives it back: each stage's times from 0, its start on the
    acquisition's clock in settings["t0"]."""
    stages = {}
    for n, st in run.stages.items():
        t0 = float(st.t[0])
        stages[n] = Stage(n, st.t - t0, dict(st.channels), st.excitation, {**st.settings, "t0": t0})
    return Run(stages, dict(run.attrs), run.source)


def test_a_stiffness_drift_is_fitted_on_the_session_clock_of_a_rig_run():
    run, truth, extras, baseline = concealed_run("parameter_drift", strength=2.0, seed=5, duration=3.0)
    rig = as_rig_file(run)
    assert all(st.t[0] == 0.0 for st in rig.stages.values())
    assert [rank.session_start(st) for st in rig.stages.values()] == [float(st.t[0]) for st in run.stages.values()]
    d = diagnose(rig, baseline, candidates=["parameter_drift"])
    assert [m["id"] for m in d.missing] == ["parameter_drift"]
    true = AugmentedModel(truth, extras).get("drift")
    assert d.best.get("drift") == pytest.approx(true, rel=0.2)

"""The optional constant input offset (issue 14): a model driven by g (u - b), b fitted by the output-error
polish when ReconSettings(input_offset=True); off by default, where nothing changes."""
from __future__ import annotations

import warnings

import numpy as np
import pytest

from recon import ReconSettings, reconstruct
from recon.model import UNITS, HystereticModel
from recon.output_error.problem import OutputError, parameter_keys
from recon.testing.truth import sdof_run
from shakerlab.run_data import Run, Stage


@pytest.fixture(scope="module")
def force_runs():
    run, truth = sdof_run("force", snr_db=60.0, duration=6.0, seed=3)
    b = 0.2 * float(np.std(run.stage("nonlinear").channels["force"]))
    stages = {n: Stage(n, st.t, dict(st.channels, force=st.channels["force"] + b), st.excitation)
              for n, st in run.stages.items()}
    return run, Run(stages, source="force sensor with an offset"), truth, b


def test_the_offset_is_subtracted_from_the_input_and_serialised(force_runs):
    run, _, truth, b = force_runs
    st = run.stage("nonlinear")
    u = st.channels["force"]
    with_b = HystereticModel.from_dict(dict(truth.to_dict(), parameters=dict(truth.to_dict()["parameters"],
                                                                             input_offset=b)))
    assert with_b.input_offset == b
    y1 = with_b.simulate(st.t, u + b)[0]
    y0 = truth.simulate(st.t, u)[0]
    np.testing.assert_allclose(y1, y0, rtol=0, atol=1e-12 * np.max(np.abs(y0)))
    d = with_b.to_dict()
    assert d["parameters"]["input_offset"] == b and d["units"]["input_offset"] == "N"
    assert f"(F - {b:.6g})" in d["equation"]
    # without it: no key, the shared units, the old equation, and no parameter in the fits
    plain = truth.to_dict()
    assert "input_offset" not in plain["parameters"] and plain["units"] is UNITS and "(F" not in plain["equation"]
    assert "input_offset" not in parameter_keys(truth)
    assert parameter_keys(with_b)[-1] == "input_offset"
    oe = OutputError(with_b, [truth.fit_item(st)])
    assert oe.build(np.zeros(len(oe.keys))).input_offset == b


def test_reconstruct_fits_the_offset_only_when_asked(force_runs):
    _, off, truth, b = force_runs
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        default = reconstruct(off, ReconSettings()).to_dict()
        fitted = reconstruct(off, ReconSettings(input_offset=True)).to_dict()
    assert "input_offset" not in default["parameters"]
    # measured: b recovered to 0.01 %; validation NRMSE 0.090 against 0.62 without the offset;
    # inv_m 1.845 (truth 2.0) against 0.709
    assert fitted["parameters"]["input_offset"] == pytest.approx(b, rel=0.01)
    assert fitted["validation"]["nrmse"] < 0.3 * default["validation"]["nrmse"]
    assert abs(fitted["parameters"]["inv_m"] / 2.0 - 1) < abs(default["parameters"]["inv_m"] / 2.0 - 1)

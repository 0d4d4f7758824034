"""The independent generator conceals two effects at once (issue 74, "two effects at once")."""
import numpy as np
import pytest

from recon.testing import independent as ind


def _system():
    return ind.random_system(np.random.default_rng([3, 74]), hysteresis=True, cubic=True)


# acceptance tier (two full recordings, > 10 s on 2 cores): the fast tier records a pair through the same
# path (simulate's ``also``) in test_stress_blocks.py::test_pair_recording_conceals_both_effects
@pytest.mark.slow
def test_second_effect_is_added_and_the_first_kept():
    alone = ind.simulate(_system(), "paper", 1000.0, "coulomb_friction", 1.0, seed=3)
    pair = ind.simulate(_system(), "paper", 1000.0, "coulomb_friction", 1.0, seed=3,
                        also=(("parameter_drift", 1.0),))
    for k, v in alone["effect_parameters"].items():
        assert pair["effect_parameters"][k] == v
    assert abs(pair["effect_parameters"]["drift_rate"]) == pytest.approx(5e-4)
    assert pair["also"] == [["parameter_drift", 1.0]]
    assert "also" not in alone
    # the drift changes the recording
    a, b = alone["stages"]["validation"]["x_tip"], pair["stages"]["validation"]["x_tip"]
    assert np.std(a - b) > 1e-3 * np.std(a)


@pytest.mark.parametrize("other", ["contact_stiffness", "coulomb_friction", "cubic_stiffness"])
def test_second_effect_must_be_another_physical_one(other):
    with pytest.raises(ValueError):
        ind.simulate(_system(), "paper", 1000.0, "coulomb_friction", 1.0, seed=3, also=((other, 1.0),))

"""The diagnosis's fits hold what they are read for, not every simulation: a fit's simulated
output (FitResult.sims) is simulated again when first read, from the starts the fit's own
simulation took, to the bit; the Jacobian's shifted columns are formed in place with the same
arithmetic."""
import numpy as np

from recon.diagnosis import rank
from recon.diagnosis.augmented import AugmentedModel
from recon.diagnosis.jacobian import shift_columns
from recon.testing.concealed import concealed_run


def test_fit_simulates_its_output_again_to_the_bit_when_read():
    run, _, _, baseline = concealed_run(None, excitation="base", duration=2.0, seed=3)
    data = rank.prepare(run, baseline)
    assert any(d.held.any() and not d.fit.any() for d in data)       # a held-out stage: its start is fitted
    fr = rank.fit(AugmentedModel(baseline, {}), ["c_m", "k_m", "gamma"], data, max_nfev=3)
    assert fr._sims is None
    sims = rank.simulate_all(fr.model, fr.sim_stages)            # what the fit itself simulated
    assert all(np.array_equal(a, b) for a, b in zip(fr.sims, sims))
    assert fr.sims is fr.sims                                    # kept once read
    held = np.concatenate([(ys - d.y)[d.held] for d, ys in zip(fr.sim_stages, fr.sims)])
    assert np.array_equal(held, fr.resid_held)


def test_shift_columns_in_place_is_the_interpolation_formula():
    rng = np.random.default_rng(0)
    S = rng.normal(size=(500, 4))
    for delay in (0.0, 3.3e-4, -1.7e-4, 2e-2):
        dt = 1e-4
        n = S.shape[0]
        idx = np.clip(np.arange(n) - delay / dt, 0.0, n - 1.0)
        i0 = np.minimum(np.floor(idx).astype(np.int64), n - 2)
        frac = (idx - i0)[:, None]
        expected = S if delay == 0.0 else S[i0] * (1.0 - frac) + S[i0 + 1] * frac
        got = shift_columns(S, delay, dt)
        assert np.array_equal(got, expected)

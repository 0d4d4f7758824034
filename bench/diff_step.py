"""Finite-difference step of the output-error fits, measured per simulator (issue 12).

    python bench/diff_step.py          # about 1 min

scipy's least_squares takes the Jacobian by forward differences with a relative step
(``diff_step``). Too large a step biases it by the curvature, too small a step drowns it in the
simulator's rounding noise. For each simulator the table gives the relative error of the
forward-difference Jacobian, ||J_h - J_ref|| / ||J_ref|| (Frobenius), against a reference taken
by central differences at h = 1e-6 (truncation ~h^2), at the ground-truth parameters:

- rk4: recon.simulation.rk4 (the one RK4 kernel: the polish, the term selection, the simpler
  models' fits, the uncertainty ensemble and the diagnosis's augmented fits all simulate with it),
  base and force excitation, fixed and from-the-data start states;
- rk4 + friction + contact: the diagnosis's augmented model (a steep tanh and a kink), its
  parameters relative;
- newmark: recon.simulation.newmark.simulate_chain (the Bouc-Wen benchmark's generation chain:
  Newmark with Newton iterations, up- and down-sampling filters).
"""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from recon.diagnosis.augmented import AugmentedModel  # noqa: E402
from recon.output_error.problem import OutputError, get_parameter, set_parameter  # noqa: E402
from recon.simulation.newmark import NewmarkParameters, simulate_chain  # noqa: E402
from recon.testing.truth import sdof_run  # noqa: E402

STEPS = (1e-4, 1e-5, 1e-6, 1e-7, 1e-8, 1e-9)
REFERENCE = 1e-6


def jacobian(f, x0, h, central=False):
    r0 = f(x0)
    J = np.empty((r0.size, x0.size))
    for i in range(x0.size):
        e = np.zeros_like(x0)
        e[i] = h * max(1.0, abs(x0[i]))
        J[:, i] = (f(x0 + e) - (f(x0 - e) if central else r0)) / (e[i] * (2 if central else 1))
    return J


def errors(f, x0):
    ref = jacobian(f, x0, REFERENCE, central=True)
    return [float(np.linalg.norm(jacobian(f, x0, h) - ref) / np.linalg.norm(ref)) for h in STEPS]


def rk4_case(excitation, with_start):
    run, truth = sdof_run(excitation, snr_db=60.0, seed=0, duration=4.0)
    data = []
    for name in ("linear", "nonlinear"):
        st = run.stage(name)
        u = truth.stage_input(st)
        item = truth.fit_item(st, u)
        data.append(item if with_start else item[:3])
    prob = OutputError(truth, data)
    return prob.residual, np.zeros(len(prob.keys)), len(prob.keys)


def augmented_case():
    """The diagnosis's augmented model: Coulomb friction (tanh(y'/1e-4 m/s)) and a one-sided
    contact spring (a kink at the gap) on the base truth, their parameters free."""
    run, truth = sdof_run("base", snr_db=60.0, seed=0, duration=4.0)
    st = run.stage("nonlinear")
    u = truth.stage_input(st)
    y = st.y
    am = AugmentedModel(truth, {"mu": 0.02 * truth.k_m * np.std(y), "kc": 0.3 * truth.k_m,
                                "gap": 1.2 * np.std(y)})
    keys = ["c_m", "k_m", "alpha_m", "gamma", "delta", "x:mu", "x:kc", "x:gap"]
    x0 = np.array([get_parameter(am, k) for k in keys])
    y_truth = am.simulate(st.t, u, st.channels["x_base"])[0]

    def resid(p):
        m = am.copy()
        for k, v in zip(keys, x0 * (1.0 + p)):
            set_parameter(m, k, v)
        return (m.simulate(st.t, u, st.channels["x_base"])[0] - y_truth) / np.std(y)
    return resid, np.zeros(len(keys)), len(keys)


def newmark_case():
    p = NewmarkParameters.from_benchmark(m=2.0, c=10.0, k=5e4, alpha=5e4, beta_gamma=800.0, beta_delta=-1100.0)
    fs = 750.0
    rng = np.random.default_rng(0)
    u = np.convolve(rng.normal(0.0, 50.0, 3000), np.ones(4) / 4, mode="same")      # N, about the benchmark's level
    y = simulate_chain(p, u, fs)
    theta0 = np.array([getattr(p, k) for k in NewmarkParameters.NAMES])

    def resid(x):
        q = NewmarkParameters(**dict(zip(NewmarkParameters.NAMES, theta0 * (1.0 + x))))
        return simulate_chain(q, u, fs) - y
    return resid, np.zeros(6), 6


def main():
    cases = [("rk4, base, from rest", *rk4_case("base", False)),
             ("rk4, base, recorded start", *rk4_case("base", True)),
             ("rk4, force, recorded start", *rk4_case("force", True)),
             ("rk4 + friction + contact", *augmented_case()),
             ("newmark chain (benchmark)", *newmark_case())]
    print(f"relative error of the forward-difference Jacobian against central differences at {REFERENCE:g}\n")
    print(f"{'simulator':30s} {'params':>6s} " + " ".join(f"{h:>9.0e}" for h in STEPS))
    for name, f, x0, n in cases:
        e = errors(f, x0)
        print(f"{name:30s} {n:6d} " + " ".join(f"{v:9.1e}" for v in e))


if __name__ == "__main__":
    main()

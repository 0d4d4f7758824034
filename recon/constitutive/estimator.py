"""The constitutive problem: the force law of a component test, by the estimator's steps.

    from recon.constitutive.estimator import reconstruct_constitutive
    result = reconstruct_constitutive(run)      # a run whose mode is "constitutive"

Steps (the same ones as for a structure, composed for a force law):

1. signals: Savitzky-Golay smoothing and derivatives (recon.constitutive.signals);
2. agent-model sparse regression with the automatic threshold, lambda/alpha/fn extraction,
   structured refit and delta (recon.constitutive.equation_error);
3. output-error polish, by variable projection, of the law's structure on the fitted stage
   (recon.constitutive.output_error); with a command channel (``command_law``), the
   command-dependent law (c, alpha linear in the lagged command) from the constant law;
4. term revision by the output error's information criterion;
5. validation: the force predicted on every ``validation*`` stage from its recorded motion
   (and command), NRMSE against the recorded force.

The result's ``to_dict`` has the keys of ``ReconResult.to_dict``; ``validation.nrmse`` is
on the force.
"""
from __future__ import annotations

import math
import time
from dataclasses import asdict, dataclass, field, replace

import numpy as np

from recon.constitutive.equation_error import equation_error
from recon.constitutive.law import ConstitutiveLaw
from recon.constitutive.output_error import ForceOutputError, polish, revise_terms
from recon.constitutive.signals import ComponentSignals, component_signals
from recon.determinism import single_thread_blas
from recon.differentiation import estimate_spectrum
from recon.estimator.adequacy import verdict
from recon.settings_fields import bounded as _f, check
from recon.validation import nrmse
from shakerlab import __version__
from shakerlab.errors import UserFacingError
from shakerlab.modes import COMMAND_CHANNEL, CONSTITUTIVE, run_mode
from shakerlab.run_data import Run

ETA_GRID = np.geomspace(1.0, 1000.0, 13)      # 1/s: starts of the command lag searched


@dataclass
class ConstitutiveSettings:
    library_order: int = 5
    n_folds: int = 5
    polish: bool = True
    term_selection: bool = True
    command_law: bool | str = "auto"   # "auto": when the fitted stage has a command that varies
    fit_stage: str = "nonlinear"
    # inertia of the moving parts: "none", "fit" (a term m x'', m fitted) or a known mass [kg]
    inertia: str | float = "none"
    window: int | None = None
    sg_order: int | None = None
    # the tuned numbers of the component-test estimator and of its diagnosis (recon.settings_fields:
    # a meaning, a unit and a range each, checked when the settings are made)
    fit_rate: float = _f(2000.0, "the projected output-error fits take a record sampled faster than twice "
                         "this rate on every q-th sample (its rate stays at least this)", "Hz", 0.0, 1e7,
                         lo_open=True)
    negligible: float = _f(0.002, "term revision: fn terms whose rms force is below this share of the elastic "
                           "force K x go at once (kept only if the BIC does not grow)",
                           "fraction of the elastic force", 0.0, 1.0)
    z_margin: float = _f(0.1, "the equation error's second clustering leaves out the rows whose implied |z| is "
                         "below this fraction of half its 1-99 % range", "fraction", 0.0, 1.0)
    min_gain: float = _f(0.1, "the law's diagnosis names a candidate that cuts the held-out force NRMSE by at "
                         "least this share of the null fit's", "fraction", 0.0, 1.0)

    def __post_init__(self):
        check(self)
        if not (self.inertia in ("none", "fit") or (isinstance(self.inertia, (int, float))
                                                     and math.isfinite(self.inertia) and self.inertia >= 0)):
            raise UserFacingError(f"inertia must be 'none', 'fit' or a mass >= 0 in kg, got {self.inertia!r}")

    @property
    def known_mass(self) -> float:
        return float(self.inertia) if isinstance(self.inertia, (int, float)) else 0.0

    def to_dict(self):
        return asdict(self)


@dataclass
class ConstitutiveResult:
    law: ConstitutiveLaw
    equation_error: dict
    sparse: dict
    differentiation: dict
    validation: dict
    settings: ConstitutiveSettings
    adequacy: dict = field(default_factory=dict)
    timings: dict = field(default_factory=dict)
    signals: dict = field(default_factory=dict, repr=False)

    @property
    def model(self) -> ConstitutiveLaw:
        return self.law

    def to_dict(self) -> dict:
        d = self.law.to_dict()
        ee = self.equation_error
        return {
            "excitation": CONSTITUTIVE,
            "parameters": d["parameters"],
            "units": d["units"],
            "convention": d["convention"],
            "equation": d["equation"],
            "validation": self.validation,
            "linear_step": {"note": "no separate linear step: c, K = k + alpha and f0 are columns of the "
                                    "agent-model regression of the force", **ee.get("equation_error", {})},
            "nonlinear_step": {"library": ee.get("library", {}), "hysteresis": ee.get("hysteresis", {}),
                               "sparse_regression": self.sparse, "passes": ee.get("passes", []),
                               "polish": self.law.provenance.get("output_error_polish", {}),
                               "term_revision": self.law.provenance.get("term_revision", [])},
            "settings": {"differentiation": self.differentiation, "threshold": self.sparse.get("threshold"),
                         "library_order": self.settings.library_order, "form": "joint", "refit": True,
                         "mode": CONSTITUTIVE, "fit_stage": self.settings.fit_stage,
                         "command_law": self.law.commanded},
            "adequacy": self.adequacy,
            "timings_s": self.timings,
            "software": {"shakerlab": __version__},
        }


def admissible(law: ConstitutiveLaw) -> bool:
    """Finite, a dissipative loop (alpha > 0, gamma + delta > 0) and a positive small-amplitude
    stiffness; with a command law, alpha stays positive over the recorded command range (checked
    by the caller)."""
    vals = [law.c, law.k, law.alpha, law.gamma, law.delta, law.f0, *law.fn.values(), law.c1, law.alpha1, law.eta]
    return bool(all(math.isfinite(v) for v in vals) and law.alpha > 0 and law.lam > 0 and law.K > 0)


def wants_command(stage, setting) -> bool:
    """Fit the command-dependent law? ``setting`` "auto": when the stage's command varies (its
    range over 20 times its sample noise); True needs a command channel; False never."""
    cmd = stage.channels.get(COMMAND_CHANNEL)
    # noise of the command from its first differences (robust: a switched command's steps are rare)
    noise = float(np.median(np.abs(np.diff(cmd)))) * 1.4826 / np.sqrt(2) if cmd is not None else 0.0
    varies = cmd is not None and float(np.ptp(cmd)) > 20 * noise     # white noise alone: ptp ~ 8-11 x
    if setting == "auto":
        return bool(varies)
    if setting and cmd is None:
        raise UserFacingError(f"stage {stage.name!r}: a command-dependent law needs a command channel (CSV column cmd)")
    return bool(setting)


def command_start(law: ConstitutiveLaw, items: list[ComponentSignals], fit_rate: float):
    """The command law's start: the constant law with c1 = alpha1 = 0 and the lag eta of the grid
    whose projected output error is lowest (the linear parameters, c1 and alpha1 among them,
    are solved at every trial; ``fit_rate``: ConstitutiveSettings.fit_rate)."""
    best = None
    for eta in ETA_GRID:
        trial = ConstitutiveLaw(**{**law.__dict__, "eta": float(eta)})
        prob = ForceOutputError(trial, items, fit_eta=False, fit_rate=fit_rate)
        r = prob.residual(np.zeros(len(prob.keys)))
        cost = float(r @ r)
        if best is None or cost < best[0]:
            best = (cost, trial)
    return best[1], {"eta_grid": [float(e) for e in ETA_GRID], "eta_start": best[1].eta}


def grid_start(items: list[ComponentSignals], commanded: bool, fit_rate: float):
    """A start for the projected polish without the equation-error estimate: the (gamma, delta)
    of a grid (lambda = gamma + delta from 0.3 to 30 over the rms displacement, gamma/lambda 0.5,
    0.75, 1) whose projected output error is lowest; no fn terms, damping and offset in
    (``fit_rate``: ConstitutiveSettings.fit_rate)."""
    rms = float(np.sqrt(np.mean(np.concatenate([it.y - it.y.mean() for it in items]) ** 2))) or 1.0
    best = None
    for lam in np.geomspace(0.3, 30.0, 9) / rms:
        for share in (0.5, 0.75, 1.0):
            trial = ConstitutiveLaw(c=1.0, k=0.0, alpha=1.0, gamma=share * lam, delta=(1 - share) * lam, f0=0.0,
                                    eta=float(ETA_GRID[6]) if commanded else 0.0)
            prob = ForceOutputError(trial, items, fit_eta=False, fit_rate=fit_rate)
            r = prob.residual(np.zeros(len(prob.keys)))
            cost = float(r @ r)
            if best is None or cost < best[0]:
                best = (cost, prob.build(np.zeros(len(prob.keys))))
    law = best[1]
    if commanded:
        law = ConstitutiveLaw(**{**law.__dict__, "c1": 0.0, "alpha1": 0.0, "eta": 0.0})
    return law


@single_thread_blas
def reconstruct_constitutive(run: Run, settings: ConstitutiveSettings | None = None,
                             validate_law: bool = True) -> ConstitutiveResult:
    s = settings or ConstitutiveSettings()
    if run_mode(run) != CONSTITUTIVE:
        raise UserFacingError(f"{run.source or 'run'}: not a component test (mode {run_mode(run)!r}); import it with "
                              f"`shakerlab import --constitutive`")
    timings = {}
    stage = run.stage(s.fit_stage)
    t0 = time.perf_counter()
    fit_mass = s.inertia == "fit"
    sig = component_signals(stage, s.window, s.sg_order, third=fit_mass or s.known_mass > 0)
    if s.known_mass:      # a known inertia force is taken off the recorded force
        m = s.known_mass
        sig = replace(sig, F=sig.F - m * sig.ddy, dF=sig.dF - m * sig.dddy, F_raw=sig.F_raw - m * sig.ddy)
    timings["signals"] = time.perf_counter() - t0
    t1 = time.perf_counter()
    with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
        law, info, sp = equation_error(sig, s.library_order, s.n_folds, fit_mass=fit_mass, z_margin=s.z_margin)
    timings["equation_error"] = time.perf_counter() - t1
    law.provenance = {"method": "agent-model sparse regression of the force (shakerlab recon.constitutive)",
                      "software": f"shakerlab {__version__}", "settings": s.to_dict(), "source": run.source,
                      "differentiation": sig.choice, "equation_error_estimate": law.parameters()}
    info["equation_error_admissible"] = admissible(law)
    commanded = wants_command(stage, s.command_law)
    if s.polish:
        t2 = time.perf_counter()
        prov = law.provenance
        start = "equation-error estimate"
        if not info["equation_error_admissible"]:
            # a law the agent model does not hold for (a command-dependent one: the regression is of
            # the constant law) can give an inadmissible estimate; the projected fit needs only
            # gamma and delta, so a grid start is cheap
            law = grid_start([sig], commanded, s.fit_rate)
            start = "grid (the equation-error estimate is not admissible)"
            if fit_mass:
                law = ConstitutiveLaw(**{**law.__dict__, "mass": 1e-9})
        law, pinfo = polish(law, [sig], fit_rate=s.fit_rate)
        pinfo["start"] = start
        if commanded:
            start, cinfo = command_start(law, [sig], s.fit_rate)
            law, cp = polish(start, [sig], max_nfev=100, fit_rate=s.fit_rate)
            pinfo = {"constant_law": pinfo, "command_law": dict(cp, **cinfo)}
        timings["polish"] = time.perf_counter() - t2
        steps = []
        if s.term_selection and law.fn:
            t3 = time.perf_counter()
            law, steps = revise_terms(law, [sig], fit_rate=s.fit_rate, negligible=s.negligible)
            timings["term_revision"] = time.perf_counter() - t3
        law.provenance = dict(prov, output_error_polish=pinfo, term_revision=steps)
    if s.known_mass:
        law.mass = s.known_mass
    t4 = time.perf_counter()
    val = validate(law, run, s) if validate_law else {"nrmse": float("nan"), "stage": None}
    timings["validation"] = time.perf_counter() - t4
    result = ConstitutiveResult(law=law, equation_error=info, sparse=sp.summary(), differentiation=sig.choice,
                                validation=val, settings=s, timings=timings,
                                signals={"t": sig.t, "y": sig.y, "dy": sig.dy, "F": sig.F_raw,
                                         "cmd": sig.cmd})
    result.adequacy = assess(law, val, run)
    return result


def predict(law: ConstitutiveLaw, stage, settings: ConstitutiveSettings | None = None):
    """(t, recorded force, predicted force, smoothed x) of a stage, simulated from the state the
    law implies at its first sample."""
    s = settings or ConstitutiveSettings()
    sig = component_signals(stage, s.window, s.sg_order, for_regression=False)
    cmd = sig.cmd if law.commanded else None
    if law.commanded and cmd is None:
        raise UserFacingError(f"stage {stage.name!r}: the law depends on a command and the stage has none")
    u0 = None if cmd is None else float(cmd[0])
    w0 = law.start_state(sig.F[0], sig.y[0], sig.dy[0], u0, sig.ddy[0])
    F, _, _ = law.simulate(sig.dt, sig.y, sig.dy, cmd, w0, sig.ddy)
    return sig.t, sig.F_raw, F, sig.y


def validate(law: ConstitutiveLaw, run: Run, s: ConstitutiveSettings | None = None) -> dict:
    s = s or ConstitutiveSettings()
    names = [n for n in run.stages if n.startswith("validation")] or [s.fit_stage]
    out = {}
    for n in names:
        _, F, Fp, _ = predict(law, run.stage(n), s)
        out[n] = nrmse(Fp, F)
    main = names[0]
    return {"nrmse": out.get(main, float("nan")), "stage": main, "per_stage": out, "quantity": "force",
            "fitted_on_validation_stage": main == s.fit_stage}


def assess(law: ConstitutiveLaw, validation: dict, run: Run) -> dict:
    """The verdict, with the keys of recon.estimator.adequacy.assess (the noise floor is the
    force's)."""
    floor = None
    st = validation.get("stage")
    if st in run.stages:
        f = run.stage(st).channels["force"]
        rms = float(np.std(f))
        floor = float(estimate_spectrum(f, run.stage(st).dt).noise_std) / rms if rms > 0 else None
    out = verdict(admissible(law), validation.get("nrmse", float("nan")), floor, len(law.fn),
                  bool(validation.get("fitted_on_validation_stage")), "law")
    if out["verdict"] != "adequate":
        out["advice"] = "look at the loop overlay of the report; a term the library lacks (backlash, a gap) shows there"
    return out

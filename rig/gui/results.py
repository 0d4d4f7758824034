"""The after-run view: what the results panel shows, computed off the GUI thread (no Qt here).

:func:`view_of_run_file` reads a run file (``.h5``; an ``.npz`` of arrays is reconstructed and
shown but nothing is written into it); when it already holds a
reconstruction result (``entry/results/reconstruction_NNN``, written by
``shakerlab demo``, ``shakerlab reconstruct`` or this GUI) the newest one is
shown, otherwise (or with ``reconstruct=True``) the governing equation is
reconstructed with :func:`recon.estimator.pipeline.reconstruct` and written back into
the file (when it was closed cleanly). The model is then simulated on the
validation stage to give the measured-vs-simulated overlay and the
hysteresis loop. A diagnosis is shown only when the file holds a
``diagnosis_NNN`` result.
"""
from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np


PARAM_ORDER = ("c_m", "k_m", "alpha_m", "gamma", "delta", "inv_m")


@dataclass
class ResultView:
    source: str
    status: str                      # the run's status (complete, aborted, ...)
    equation: str
    parameters: list                 # rows: (name, value, unit, true or None)
    nrmse: float                     # of the overlay: simulated vs measured y on validation_stage
    validation_stage: str | None
    overlay: tuple | None            # (t, y measured, y simulated) [s, m, m]
    loop: tuple | None               # (y, z) simulated on loop_stage [m, m/s^2]
    measured_loop: tuple | None      # (y, z) implied by the data of loop_stage and the identified model
    loop_stage: str | None = None    # nonlinear (the largest loop) when recorded, else the validation stage
    diagnosis: str | None = None
    origin: str = ""                 # "stored result <group>" or "reconstructed now"
    notes: list = field(default_factory=list)
    # axis labels and legends (a component test shows forces): keys of STRUCTURE_LABELS
    labels: dict = field(default_factory=dict)
    verdict: tuple | None = None     # (level green/amber/red/grey, the one sentence): verdict_line(adequacy)


# the labels of a structure's view; a component test's view (constitutive mode) overrides them
STRUCTURE_LABELS = {"overlay": ("y", "m"), "loop_left": ("z", "m/s²"), "loop_bottom": ("y", "m"),
                    "loop_title": "hysteresis loop z vs y", "loop_last_third": True,
                    "measured_name": "data: −x_base'' − y'' − c_m y' − k_m y − fn"}
FORCE_LABELS = {"measured_name": "data: inv_m F − y'' − c_m y' − k_m y − fn"}
COMPONENT_LABELS = {"overlay": ("F", "N"), "loop_left": ("F", "N"), "loop_bottom": ("x", "m"),
                    "loop_title": "force-displacement loop", "loop_last_third": False,
                    "measured_name": "recorded force"}


def verdict_line(adequacy: dict | None) -> tuple[str, str]:
    """(colour, sentence) of a reconstruction's adequacy (``result.adequacy``): the command line's
    one sentence (recon.estimator.adequacy.verdict_summary) with its level as the banner's colour:
    green adequate, amber a simpler model standing in or no verdict, red inadequate."""
    from recon.estimator.adequacy import verdict_summary  # lazy: recon, loaded when a result is shown
    summary = verdict_summary(adequacy)
    colour = {"good": "green", "warning": "amber", "bad": "red"}[summary["level"]]
    if not adequacy:
        colour = "grey"
    return colour, summary["text"]


def fn_unit(term: str, component: bool = False) -> str:
    """The unit of an fn coefficient: per unit mass a term y^p y'^r has m^(1-p-r) s^(r-2); in a
    component test's force law (N) N m^(-p-r) s^r. "" for a name that is not a monomial."""
    from recon.library import monomials  # heavy: recon, loaded when a result is shown

    try:
        p, r = monomials.parse(term)
    except Exception:  # noqa: BLE001 - any name that is not a monomial has no unit here
        return ""
    powers = [("N", 1 if component else 0), ("m", -p - r if component else 1 - p - r), ("s", r if component else r - 2)]
    num = " ".join(u if e == 1 else f"{u}^{e}" for u, e in powers if e > 0)
    den = [u if e == -1 else f"{u}^{-e}" for u, e in powers if e < 0]
    if not den:
        return num or "1"
    den_text = den[0] if len(den) == 1 else "(" + " ".join(den) + ")"
    return f"{num or '1'}/{den_text}"


def _latest(results: dict, kind: str):
    names = sorted(n for n in results if n.startswith(kind + "_"))
    return (names[-1], results[names[-1]]) if names else (None, None)


def _write_back(path: Path, payload: dict, text: str, notes: list) -> str:
    """Store a reconstruction just made in the run file; returns the origin's suffix, or adds the
    reason it was not stored to ``notes``."""
    from shakerlab.jsonsafe import clean  # heavy: recon, loaded when a result is shown
    from shakerlab.runfile.results import store_result  # heavy: recon, loaded when a result is shown

    group, note = store_result(path, "reconstruction", clean(payload), text=text)
    if group is None:
        notes.append(note)
        return ""
    return f", written to entry/results/{group}"


def _rows(params: dict, units: dict, truth: dict | None) -> list:
    truth = truth or {}
    rows = []
    for name in PARAM_ORDER:
        if name in params and params[name] is not None:
            rows.append((name, float(params[name]), str(units.get(name, "")),
                         float(truth[name]) if name in truth else None))
    tfn = truth.get("fn_m", {}) or {}
    for name, value in (params.get("fn_m") or {}).items():
        rows.append((f"fn_m[{name}]", float(value), fn_unit(name), float(tfn[name]) if name in tfn else None))
    for name in tfn:
        if name not in (params.get("fn_m") or {}):
            rows.append((f"fn_m[{name}]", 0.0, fn_unit(name), float(tfn[name])))
    return rows


def _diagnosis_text(payload: dict) -> str:
    for key in ("text", "summary", "diagnosis"):
        if isinstance(payload.get(key), str) and payload[key].strip():
            return payload[key]
    return json.dumps(payload, indent=2, default=str)


def data_loop(model, stage):
    """(y, z) implied by a stage's data and the model's other terms, last third:
    ``z = -x_base'' - y'' - c_m y' - k_m y - fn(y, y')`` (base excitation) or
    ``z = inv_m F - y'' - c_m y' - k_m y - fn(y, y')`` (force excitation, F the model's input), with
    Savitzky-Golay derivatives."""
    from recon.differentiation import choose_window, derivatives  # heavy: recon, loaded when a result is shown

    n = stage.t.size
    if model.excitation != "base":
        x = stage.y[2 * n // 3:]
        ch = choose_window({"x": x}, stage.dt, deriv=2, for_regression=False)
        y = derivatives(x, stage.dt, ch.window, ch.order, 2)
        u = model.stage_input(stage)[2 * n // 3:]
        force = (model.inv_m or 0.0) * (u - (model.input_offset or 0.0))
        z = force - y[2] - model.c_m * y[1] - model.k_m * y[0] - model.fn(y[0], y[1])
        keep = slice(ch.window, max(ch.window, y[0].size - ch.window))
        return y[0][keep], z[keep]
    xb, xt = stage.channels["x_base"][2 * n // 3:], stage.channels["x_tip"][2 * n // 3:]
    dt = stage.dt
    ch = choose_window({"x_tip": xt, "x_base": xb}, dt, deriv=2, for_regression=False)
    y = derivatives(xt - xb, dt, ch.window, ch.order, 2)
    ddb = derivatives(xb, dt, ch.window, ch.order, 2)[2]
    z = -ddb - y[2] - model.c_m * y[1] - model.k_m * y[0] - model.fn(y[0], y[1])
    keep = slice(ch.window, max(ch.window, y[0].size - ch.window))   # Savitzky-Golay edges left out
    return y[0][keep], z[keep]


def view_of_run_file(path: str | Path, reconstruct: bool = False, write_back: bool = True,
                     truth: dict | None = None, law: str | Path | None = None) -> ResultView:
    """The results view of a run file (see the module docstring). Raises UserFacingError on bad files.

    ``truth``: the simulated specimen's true parameters (runs on the simulated rig); shown beside the
    identified ones and stored with a new result.
    ``law``: a component test's law JSON (docs/constitutive.md): the model shown is that law with
    the specimen's mass and support fitted on this run (recon.constitutive.bridge); nothing is
    written back.
    """
    from recon.model import HystereticModel  # heavy: recon, loaded when a result is shown
    from shakerlab.runfile.results import read_results  # heavy: recon, loaded when a result is shown
    from shakerlab.runfile.reader import read_info  # heavy: recon, loaded when a result is shown
    from shakerlab.runfile.reader import load_run  # heavy: recon, loaded when a result is shown

    path = Path(path)
    run = load_run(path)
    notes = []
    if path.suffix == ".npz":  # plain arrays: no metadata, no stored results, nothing written back
        info, results = {"status": "imported (.npz)", "clean_close": False}, {}
        write_back = False
    else:
        info = read_info(path)
        results = read_results(path)
    if info.get("mode") == "constitutive":
        return component_view(path, run, info, results, reconstruct, write_back)
    group, payload = _latest(results, "reconstruction")
    measured_loop = None
    if law is not None:
        from recon.constitutive.bridge import shaker_baseline  # heavy: recon, loaded when a result is shown
        from recon.constitutive.law import ConstitutiveLaw  # heavy: recon, loaded when a result is shown

        model, bridge = shaker_baseline(ConstitutiveLaw.load(law), run)
        payload = dict(model.to_dict(), validation={})
        origin = (f"baseline from the component law {Path(law).name}: mass {bridge['mass']:.4g} kg, support "
                  f"stiffness {bridge['support_stiffness']:.4g} N/m and damping {bridge['support_damping']:.4g} "
                  f"N s/m fitted on this run (not written back)")
    elif payload is None or reconstruct:
        from recon.estimator.pipeline import reconstruct as run_recon  # heavy: recon, loaded when a result is shown

        result = run_recon(run)
        payload = result.to_dict()
        if truth is not None:
            payload["truth"] = truth
        model = result.model
        origin = "reconstructed now"
        if write_back:
            origin += _write_back(path, payload, str(model), notes)
    else:
        model = HystereticModel.from_dict({"excitation": payload.get("excitation", "base"),
                                           "parameters": payload["parameters"]})
        origin = f"stored result {group}"
    from recon.validation import nrmse  # heavy: recon, loaded when a result is shown

    val = payload.get("validation", {}) or {}
    vstage = val.get("stage")
    if not vstage or vstage not in run.stages:
        vstage = next((n for n in run.stages if n.startswith("validation")), None)
    overlay = loop = None
    error = float("nan")
    if vstage:
        st = run.stage(vstage)
        y_sim, _, z_sim = model.simulate(st.t - st.t[0], model.stage_input(st))
        overlay = (st.t, st.y, y_sim)
        loop = (y_sim, z_sim)
        error = nrmse(y_sim, st.y)
    else:
        notes.append("the run holds no validation stage: no measured-vs-simulated overlay")
    loop_stage = vstage
    if "nonlinear" in run.stages:
        st = run.stage("nonlinear")
        y_nl, _, z_nl = model.simulate(st.t - st.t[0], model.stage_input(st))
        loop, loop_stage = (y_nl, z_nl), "nonlinear"
    if loop_stage is not None and not model.has_drive:
        measured_loop = data_loop(model, run.stage(loop_stage))
    if "nonlinear" in run.stages and law is None:
        # a loop that slides within the nonlinear stage's travel read as a friction law (its sliding
        # force): how the model holds a dry friction, as `reconstruct` says under its equation
        from recon.diagnosis.wording import friction_text, loop_reading  # heavy: recon, loaded when a result is shown

        reading = loop_reading(model, float(np.ptp(run.stage("nonlinear").y)))
        if reading:
            notes.append(friction_text(reading))
    adequacy = payload.get("adequacy")
    if adequacy is None and law is None:
        # a result stored without a verdict (a model given, not reconstructed): judged here by the
        # same rule on the same validation stage
        from recon.estimator.adequacy import assess  # heavy: recon, loaded when a result is shown

        adequacy = assess(model, {"stage": vstage, "nrmse": error, "fitted_on_validation_stage": vstage is None}, run)
    truth = payload.get("truth") or truth
    _, diag = _latest(results, "diagnosis")
    return ResultView(
        source=str(path), status=info.get("status", ""), equation=str(model),
        parameters=_rows(payload["parameters"], payload.get("units", {}), truth),
        nrmse=error, validation_stage=vstage, overlay=overlay, loop=loop,
        measured_loop=measured_loop, loop_stage=loop_stage if loop is not None else None,
        diagnosis=_diagnosis_text(diag) if diag is not None else None, origin=origin, notes=notes,
        labels={} if model.excitation == "base" else dict(FORCE_LABELS), verdict=verdict_line(adequacy),
    )


def component_view(path: Path, run, info: dict, results: dict, reconstruct: bool, write_back: bool) -> ResultView:
    """The results view of a component test (constitutive mode, docs/constitutive.md): the force
    law, the recorded vs predicted force on the validation stage, the force-displacement loop of
    the fitted stage (recorded and predicted)."""
    from recon.constitutive.estimator import ConstitutiveSettings, predict  # heavy: recon, loaded when a result is shown
    from recon.constitutive.law import ConstitutiveLaw  # heavy: recon, loaded when a result is shown
    from recon.validation import nrmse  # heavy: recon, loaded when a result is shown

    notes = []
    group, payload = _latest(results, "reconstruction")
    if payload is None or reconstruct or payload.get("excitation") != "constitutive":
        from recon.constitutive.estimator import reconstruct_constitutive  # heavy: recon, loaded when a result is shown

        result = reconstruct_constitutive(run)
        payload, law, origin = result.to_dict(), result.law, "reconstructed now"
        if write_back:
            origin += _write_back(path, payload, str(law), notes)
    else:
        law, origin = ConstitutiveLaw.from_dict(payload), f"stored result {group}"
    settings = ConstitutiveSettings()
    vstage = next((n for n in run.stages if n.startswith("validation")), None)
    overlay, error = None, float("nan")
    if vstage:
        t, F, Fp, _ = predict(law, run.stage(vstage), settings)
        overlay, error = (t, F, Fp), nrmse(Fp, F)
    else:
        notes.append("the run holds no validation stage: no recorded-vs-predicted overlay")
    loop_stage = settings.fit_stage if settings.fit_stage in run.stages else vstage
    loop = measured = None
    if loop_stage:
        _, F, Fp, x = predict(law, run.stage(loop_stage), settings)
        loop, measured = (x, Fp), (x, F)
    units = payload.get("units", {})
    params = payload["parameters"]
    rows = [(k, float(v), str(units.get(k, "")), None) for k, v in params.items() if isinstance(v, (int, float))]
    rows += [(f"fn[{k}]", float(v), fn_unit(k, component=True), None) for k, v in (params.get("fn") or {}).items()]
    notes.append("component test (constitutive mode): forces in N, the law in SI units")
    return ResultView(source=str(path), status=info.get("status", ""), equation=str(law), parameters=rows,
                      nrmse=error, validation_stage=vstage, overlay=overlay, loop=loop, measured_loop=measured,
                      loop_stage=loop_stage, origin=origin, notes=notes, labels=dict(COMPONENT_LABELS),
                      verdict=verdict_line(payload.get("adequacy")))

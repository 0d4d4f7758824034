"""A diagnosis in words, the same wherever it is shown (``shakerlab diagnose``, the reprocess
table, the operator window): the result as one statement that agrees with the mismatch listed
before it, and each located mismatch as plain text (no raw structures)."""
from __future__ import annotations

import math

from recon.diagnosis.settings import DEFAULTS, DiagnosisSettings
from shakerlab.words import nrmse_text

KINDS = {
    "time_segment": "in time", "time_trend": "a trend over the stage", "diverged": "the simulation diverged",
    "frequency_harmonic": "a harmonic", "frequency_band_at_input": "at the input's frequencies",
    "frequency_resonance": "at a resonance", "channel": "explained by",
    "state_cluster": "in a quarter of the state plane", "state_near_zero_velocity": "near zero velocity",
    "state_beyond_displacement": "beyond a displacement", "correlation_tests": "correlation tests failed",
}


def region_text(region: dict) -> str:
    """A finding's region for a person: "t 3.2-4.1 s", "at 28.4 Hz", "where y > 0.181 mm", ..."""
    parts = []
    r = dict(region or {})
    if "t_from" in r and "t_to" in r:
        parts.append(f"t {r.pop('t_from'):.3g}-{r.pop('t_to'):.3g} s")
    if "frequency_hz" in r:
        parts.append(f"at {r.pop('frequency_hz'):.4g} Hz")
    if "channel" in r:
        parts.append(f"channel {r.pop('channel')}")
    if "cluster" in r:
        parts.append(f"quadrant {r.pop('cluster')}")
    if "abs_dy_below" in r:
        parts.append(f"where |y'| < {1e3 * r.pop('abs_dy_below'):.3g} mm/s")
    if "beyond_m" in r:
        side, beyond = r.pop("y_side", 1), r.pop("beyond_m")
        parts.append(f"where y {'>' if side > 0 else '<'} {1e3 * beyond:.3g} mm")
    if "tests_failed" in r:
        parts.append("failed: " + ", ".join(str(t) for t in r.pop("tests_failed")))
    parts += [f"{k} {v:.4g}" if isinstance(v, float) else f"{k} {v}" for k, v in r.items()]
    return ", ".join(parts)


def finding_text(f: dict) -> str:
    """One located mismatch: "stage 'nonlinear', at 28.4 Hz (a harmonic): size 1.2 % of rms(y)"."""
    kind = KINDS.get(f.get("kind"), str(f.get("kind", "")).replace("_", " "))
    where = region_text(f.get("region") or {})
    size = f.get("size")
    if size is None or not math.isfinite(float(size)):
        amount = ""
    else:
        amount = f": size {100 * float(size):#.3g} %".replace(". %", " %")
    return f"stage {f.get('stage')!r}, {kind}{' ' + where if where else ''}{amount}"


# A Bouc-Wen loop (n = 1) loaded one way from z = 0 follows dz/dy = alpha - (gamma + delta) z: it is
# stiff (alpha) at first, then z approaches alpha / (gamma + delta) as 1 - exp(-(gamma + delta) y).
# That is a friction law with presliding (Dahl's): a presliding stiffness alpha, and a sliding force
# alpha / (gamma + delta) reached, within sliding_share, after a travel of -ln(1 - sliding_share) /
# (gamma + delta). A record shows both regimes when its largest travel between reversals (the
# peak-to-peak displacement) is longer than that: the loop slides there, and presliding holds at
# every reversal (sliding_share: DiagnosisSettings).


def friction_reading(alpha_m: float, gamma: float, delta: float, travel: float,
                     settings: DiagnosisSettings = DEFAULTS) -> dict | None:
    """A fitted Bouc-Wen loop read as a friction law, {presliding_stiffness_m [1/s^2], sliding_force_m
    [m/s^2], sliding_after_m [m], travel_m [m]} (per unit mass), when the loop saturates (gamma + delta > 0)
    with a positive stiffness after every reversal (gamma > 0: from the sliding force -alpha / (gamma +
    delta) the slope is alpha (1 + (gamma - delta) / (gamma + delta)) = 2 gamma alpha / (gamma + delta);
    Dahl's law has gamma = delta) and ``travel`` (the record's largest peak-to-peak displacement) reaches
    its sliding force; else None."""
    lam = gamma + delta
    if not (alpha_m > 0.0 and lam > 0.0 and gamma > 0.0
            and all(math.isfinite(v) for v in (alpha_m, gamma, delta, travel))):
        return None
    after = -math.log(1.0 - settings.sliding_share) / lam
    if travel < after:
        return None
    return {"presliding_stiffness_m": float(alpha_m), "sliding_force_m": float(alpha_m / lam),
            "sliding_after_m": float(after), "travel_m": float(travel)}


def loop_reading(model, travel: float, settings: DiagnosisSettings = DEFAULTS) -> dict | None:
    """:func:`friction_reading` of ``model``'s Bouc-Wen loop (a HystereticModel) over ``travel``."""
    return friction_reading(model.alpha_m, model.gamma, model.delta, travel, settings)


def friction_text(f: dict) -> str:
    """:func:`friction_reading` in words."""
    return (f"the loop acts as a friction law: presliding stiffness {f['presliding_stiffness_m']:.4g} 1/s^2 and "
            f"sliding force {f['sliding_force_m']:.4g} m/s^2 (per unit mass), sliding after "
            f"{1e3 * f['sliding_after_m']:.3g} mm of travel (the record travels {1e3 * f['travel_m']:.3g} mm)")


def diagnosis_text(d: dict) -> str:
    """The result of a diagnosis (``Diagnosis.to_dict()``) in one statement, consistent with the
    mismatch it located: what was named and how much it helps, else why nothing was named."""
    missing = d.get("missing_physics") or []
    un = d.get("unexplained_mismatch") or None
    if missing:
        ev = [m.get("evidence", {}) for m in missing]
        before = ev[0].get("held_out_nrmse_before")
        after = ev[-1].get("held_out_nrmse_after")
        text = (f"missing physics: {', '.join(m['id'] for m in missing)} (held-out NRMSE {nrmse_text(before)} "
                f"-> {nrmse_text(after)})")
        for m in missing:
            if m.get("as_friction"):
                text += f"; {m['id']}: {friction_text(m['as_friction'])}"
            held = [f"{k} {float(v['value']):.3g} on the {v['at_bound']} end of its fitted range"
                    for k, v in (m.get("parameters") or {}).items() if v.get("at_bound")]
            if held:
                text += f"; {m['id']}: {', '.join(held)}, not fixed by the record"
        if un:
            text += (f"; with {'it' if len(missing) == 1 else 'them'} added the held-out NRMSE {nrmse_text(un.get('held_out_nrmse'))} is still above "
                     f"the {nrmse_text(un.get('nrmse_limit'))} limit: something else is missing too")
        return text
    partly = d.get("partly_explained") or None
    if partly:
        figs = partly.get("held_out_stages") or {}
        where = "; ".join(f"stage {s!r} {nrmse_text(figs[s].get('nrmse_before'))} -> {nrmse_text(figs[s].get('nrmse_after'))}"
                          for s in partly.get("worse_on_stages", []) if s in figs)
        return (f"partly explained: {' + '.join(partly.get('ids', []))} lowers the held-out NRMSE as a whole "
                f"({nrmse_text(partly.get('held_out_nrmse_before'))} -> {nrmse_text(partly.get('held_out_nrmse_after'))}) "
                f"but predicts a held-out stage worse than the baseline as given, beyond that stage's noise ({where}): "
                f"it is not named")
    if un:
        return (f"nothing in the catalog explains the mismatch: the held-out NRMSE "
                f"{nrmse_text(un.get('held_out_nrmse'))} is above the {nrmse_text(un.get('nrmse_limit'))} limit "
                f"and no candidate is significant; physics outside the catalog, an effect this excitation "
                f"cannot separate, or a baseline too far off")
    located = len(d.get("mismatch") or [])
    return ("nothing found: the baseline predicts the held-out data within the noise limit"
            + (f", and none of the {located} disagreement(s) located is explained beyond noise by a "
               f"catalog candidate" if located else ""))

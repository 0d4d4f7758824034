"""The rows and the report of the diagnosis stress block (bench/diagnose.py --stress).

Each recording (recon.testing.stress.draw / recording) is diagnosed as `shakerlab diagnose
RUN.h5` does by default ("paper": reconstruct, then diagnose against it) for "none" and the
physical effects; for the model-term effects (cubic_stiffness, quadratic_stiffness, hysteresis)
against the truth without that term, as a user's saved model (`--baseline MODEL.json`): a paper
baseline would contain the term already. :func:`run_one` makes a row (a JSON-able dict),
:func:`report` the table and figures of rows, :func:`rescore` puts the current significance rule
to rows' stored candidate figures; the row's truth figures (:func:`oracle`,
:func:`effect_signature`, :func:`true_size`) say what the record can show at all. Blocks reported
apart from the random one (:func:`block_of`): issue 76's corner, two effects concealed together
(:func:`run_one_pair`, scored by :func:`score_pair`) and a linear stage at 0-10 dB
(:func:`run_one_weak_linear`, :func:`score_weak_linear`).
"""
from __future__ import annotations

import collections
import copy
import math
import time
import traceback
import warnings

import numpy as np

from recon.diagnosis import rank
from recon.diagnosis.augmented import AugmentedModel
from recon.diagnosis.diagnose import diagnose
from recon.diagnosis.settings import DEFAULT_RULE
from recon.output_error.problem import get_parameter
from recon.testing.runs import model_of, to_run, true_model
from recon.testing.stress import (CORNER_EFFECTS, PAIRS, concealed_effects, corner_draw, corner_recording, draw,
                                  effect_cycle, pair_draw, pair_recording, recording, weak_linear_draw,
                                  weak_linear_recording)
from shakerlab.errors import UserFacingError


def _ambiguous_ids(out: dict) -> list[str] | None:
    """The ids of an 'ambiguous' answer, if the diagnosis JSON has such a key."""
    amb = out.get("ambiguous")
    if not amb:
        return None
    ids = []
    for a in amb if isinstance(amb, list) else [amb]:
        if isinstance(a, str):
            ids.append(a)
        elif isinstance(a, dict):
            for k in ("id", "ids", "candidates"):
                v = a.get(k)
                ids += [v] if isinstance(v, str) else [x if isinstance(x, str) else x.get("id") for x in (v or [])]
    return [x for x in ids if x]


# a structural catalog id and the truth's term it stands for
STRUCTURAL_TERMS = {"quadratic_stiffness": "y^2", "cubic_stiffness": "y^3",
                    # a system with its own y^2 y' damping (the issue 76 corner's)
                    "amplitude_damping": "y^2*dy"}


def baseline_lacks(model, truth: dict) -> list[str]:
    """The structural ids whose true term the baseline does not have: on a clean recording the
    paper baseline is reconstructed from the data, and where that missed a true term, naming it
    is the right answer, not a false alarm (reported apart from the strict count)."""
    out = [cid for cid, term in STRUCTURAL_TERMS.items() if term in truth["fn_m"] and term not in model.fn_m]
    if truth.get("alpha_m", 0.0) != 0.0 and model.alpha_m == 0.0:
        out.append("hysteresis")
    return out


def contact_reach(rec: dict) -> dict | None:
    """For a contact recording: per stage, the largest displacement towards the stop over the gap
    (above 1: the contact engages). The gap sits at 55-75 % of the clean nonlinear-stage peak at
    the protocol's top level; the rig protocol stops raising its level when the distortion passes
    1.2 %, often far below it, so the contact may never engage and the record holds no contact at
    all. None for the other effects (always present)."""
    if rec["effect"] != "contact_stiffness":
        return None
    e = rec["effect_parameters"]
    return {n: float(np.max(e["side"] * (np.asarray(st["x_tip"]) - np.asarray(st["x_base"])))) / e["gap"]
            for n, st in rec["stages"].items()}


def oracle(rec: dict, data, reference) -> dict | None:
    """The truth itself put to the diagnosis's own test: the recording's true model (its system
    with the concealed effect, parameters as generated, none fitted) scored on the held-out
    samples against the diagnosis's reference (the better of the baseline as given and the null
    model) with the rule a candidate must pass (recon.diagnosis.rank.score). Not significant: the
    record does not show the effect beyond what the baseline already explains, so no candidate
    fitted to it could be named by the rule either. ``reference`` is the diagnosis's reference
    FitResult, or its held-out NRMSE alone (a stored row; the effective sample count is then
    taken from the truth's own held-out residual). ``data``: the run prepared as the diagnosis
    prepares it (rank.prepare). None for a clean recording."""
    tm = true_model(rec) if rec["effect"] != "none" else None
    if tm is None:
        return None
    am, k = tm
    fr = rank.fit(am, [], data)
    if not isinstance(reference, rank.FitResult):
        yh = np.concatenate([d.y[d.held] - d.y[d.held].mean() for d in data if d.held.any()])
        reference = rank.FitResult(model=None, cost_fit=float("nan"), mse_held=float(reference) ** 2 * float(np.mean(yh ** 2)),
                                   nrmse={}, nrmse_held=float(reference), n_held=int(yh.size), resid_held=fr.resid_held)
    s = rank.score(reference, fr, k, rank.held_noise_mse(data))
    if reference.resid_held is fr.resid_held:
        # a stored row's reference has no residual of its own: the pieces cannot be compared
        # (score would count the truth against itself, 0 of 10), so that route stays closed
        s["blocks_improved"] = None
        s["significant"] = rank.passes(s["dbic"], s["explained"], s["gain_over_noise"], s["relative_gain"], None)
    return {"held_out_nrmse": fr.nrmse_held, "reference_held_out_nrmse": reference.nrmse_held,
            **{k_: s[k_] for k_ in ("significant", "explained", "gain_over_noise", "relative_gain", "dbic",
                                    "blocks_improved")}}


def effect_off(rec: dict, am):
    """The recording's truth ``am`` (:func:`true_model`) without its concealed effect: the extras
    dropped and the effect's own fn term (amplitude damping, offset) taken out, or, for a
    structural effect, the generator's baseline (the truth without that term)."""
    if "baseline" in rec:
        return AugmentedModel(model_of(rec["baseline"], am.baseline.excitation))
    off = AugmentedModel(copy.deepcopy(am.baseline))
    for effect in [rec["effect"]] + [a[0] for a in rec.get("also", [])]:
        for term in {"amplitude_damping": ("y^2*dy",), "offset": ("y^0",)}.get(effect, ()):
            off.baseline.fn_m.pop(term, None)
    return off


def effect_signature(rec: dict, data) -> dict | None:
    """Where the concealed effect acts: the RMS of (truth - truth without the effect), each stage
    simulated from its recorded start, over the fitting and over the held-out samples of the
    diagnosis's split (rank.prepare), each over the noise floor of those samples. A fitting signature
    far below the held-out one says the fitting samples do not show the effect (for example a
    contact the nonlinear stage reaches only in its held-out end), so no fit can find it there,
    whatever the truth scores on the held-out samples. ``data`` as for :func:`oracle`. None for a
    clean recording."""
    tm = true_model(rec) if rec["effect"] != "none" else None
    if tm is None:
        return None
    on, off = tm[0], effect_off(rec, tm[0])
    parts = {"fit": [0.0, 0.0], "held": [0.0, 0.0]}     # sum of squared signature, of noise variance
    for d in data:
        a = rank.stage_output(on, d, d.initial)
        b = rank.stage_output(off, d, d.initial)
        for name, mask in (("fit", d.fit), ("held", d.held)):
            if mask.any():
                diff = np.nan_to_num(a[mask] - b[mask], nan=np.inf)
                parts[name][0] += float(np.sum(diff ** 2))
                parts[name][1] += float(mask.sum()) * d.noise ** 2
    return {f"{n}_over_noise": (math.sqrt(v[0] / v[1]) if v[1] > 0 else None) for n, v in parts.items()}


def _failed(exc: Exception) -> dict:
    return {"failed": f"{type(exc).__name__}: {exc}"[:200]}


def truth_figures(rec: dict, run, baseline, reference, kept_oracle: dict | None = None) -> dict:
    """A row's figures of its recording's truth, {"oracle": ..., "effect_signature": ...} (see
    :func:`oracle`, :func:`effect_signature`), the run prepared once for both with ``baseline``;
    ``kept_oracle`` stands in place of a new oracle. A figure that raises is {"failed": reason}
    (bench figures, not the diagnosis). {"oracle": None} for a clean recording."""
    if rec["effect"] == "none" or true_model(rec) is None:
        return {"oracle": kept_oracle}
    try:
        data = rank.prepare(run, baseline)
    except Exception as exc:  # noqa: BLE001
        return {"oracle": kept_oracle or _failed(exc), "effect_signature": _failed(exc)}
    out = {}
    for key, figure in (("oracle", lambda: kept_oracle or oracle(rec, data, reference)),
                        ("effect_signature", lambda: effect_signature(rec, data))):
        try:
            out[key] = figure()
        except Exception as exc:  # noqa: BLE001
            out[key] = _failed(exc)
    return out


def true_size(rec: dict, out: dict) -> dict | None:
    """The concealed effect's size in the unit of the diagnosis's detection limit for its candidate
    (``candidates_tested[].detection_limit``): {parameter, truth, limit}, or None (a clean recording,
    a candidate without a limit)."""
    c = next((c for c in out.get("candidates_tested", []) if c["id"] == rec["effect"]), None)
    lim = (c or {}).get("detection_limit") or {}
    tm = true_model(rec) if rec["effect"] != "none" else None
    if tm is None or lim.get("value") is None:
        return None
    am, name = tm[0], lim["parameter"]
    key = f"x:{name}" if name in am.extras else f"fn:{name}" if name in am.baseline.fn_m else name
    try:
        v = float(get_parameter(am, key))
    except (KeyError, AttributeError, ValueError):
        return None
    return {"parameter": name, "truth": v, "limit": float(lim["value"])}


# an effect whose signature on the fitting samples is below this share of its held-out signature
# (both over the noise) is one the fitting samples do not show (report; effect_signature)
FIT_SIGNATURE_SHARE = 0.1

# what each row keeps of every tested candidate (to study the decision rule offline)
CANDIDATE_KEYS = ("id", "significant", "explained", "gain_over_noise", "relative_gain", "blocks_improved", "dbic", "held_out_nrmse",
                  "compared_with_held_out_nrmse", "baseline_terms_dropped", "implausible", "failed",
                  "detection_limit", "started_from", "compared_with_nested_null", "before_nested_null", "jointly_with", "alone",
                  "held_out_stages", "worse_on_stages", "on_top_of_best", "baseline_terms_revised")


def run_one(i: int) -> dict:
    """The row of stress recording i (:func:`recon.testing.stress.draw`)."""
    return run_row(draw(i), recording)


def run_one_corner(i: int) -> dict:
    """The row of corner recording i (:func:`recon.testing.stress.corner_draw`: issue 76's corner)."""
    return run_row(corner_draw(i), corner_recording)


def run_one_pair(i: int) -> dict:
    """The row of pair recording i (:func:`recon.testing.stress.pair_draw`: two effects concealed
    together), scored by :func:`score_pair`."""
    return run_row(pair_draw(i), pair_recording)


def run_one_weak_linear(i: int) -> dict:
    """The row of weak-linear recording i (:func:`recon.testing.stress.weak_linear_draw`: the linear
    stage at 0-10 dB), scored by :func:`score_weak_linear` besides the usual figures."""
    return run_row(weak_linear_draw(i), weak_linear_recording)


# the blocks of rows: their draws and recordings (a row's block: :func:`block_of`)
BLOCKS = {"random": (draw, recording), "corner": (corner_draw, corner_recording),
          "pairs": (pair_draw, pair_recording), "weak_linear": (weak_linear_draw, weak_linear_recording)}
RUN_ONE = {"random": run_one, "corner": run_one_corner, "pairs": run_one_pair, "weak_linear": run_one_weak_linear}


def block_of(row: dict) -> str:
    """The block a row belongs to: its ``block`` field, "corner" for a corner's row (rows saved
    before the field), else "random"."""
    return row.get("block") or ("corner" if row.get("corner") else "random")


def recording_of(row: dict) -> dict:
    """The recording of a stored row, generated again from its block and index."""
    d, make = BLOCKS[block_of(row)]
    return make(d(row["index"]))


def score_pair(row: dict) -> dict:
    """The scoring of a pair row (two effects concealed together): ``right_first`` when the first id
    named is one of the two (or an ambiguous answer holds one of them), ``both`` when both are named,
    ``wrong_names`` the ids named that neither effect is. A row whose diagnosis did not answer scores
    False on both."""
    pair = concealed_effects(row)
    if row.get("status") != "ok":
        return {"pair": pair, "right_first": False, "both": False, "wrong_names": []}
    named, amb = list(row.get("named") or []), list(row.get("ambiguous") or [])
    first = row.get("first")
    right = first in pair or (first == "ambiguous" and any(e in amb for e in pair))
    return {"pair": pair, "right_first": bool(right), "both": all(e in named + amb for e in pair),
            "wrong_names": [x for x in dict.fromkeys(named + amb) if x not in pair]}


def score_weak_linear(row: dict) -> dict:
    """What a weak-linear row adds to the usual scoring: ``diagnosed`` (the diagnosis answered),
    ``exit`` (what `shakerlab diagnose` would exit with: 0 answered, 2 refused, 1 raised),
    ``refusal`` (its message) and ``linear_reported_noisy`` (the answer says the linear stage was too
    noisy for c and K; None where the baseline was not reconstructed from the run, so that no linear
    step ran)."""
    status = row.get("status")
    reconstructed = row.get("baseline") == "paper"
    noisy = any("too noisy" in w for w in row.get("baseline_warnings") or [])
    return {"diagnosed": status == "ok", "exit": {"ok": 0, "refused": 2}.get(status, 1),
            "refusal": row.get("error") if status == "refused" else None,
            "linear_reported_noisy": (noisy if reconstructed else None) if status == "ok" else None}


def run_row(d: dict, make) -> dict:
    """A row of the draw ``d``, its recording made by ``make(d)``."""
    warnings.filterwarnings("ignore")
    row = {k: v for k, v in d.items()}
    t0 = time.perf_counter()
    try:
        rec = make(d)
    except Exception as exc:  # noqa: BLE001
        row.update(status="generator failed", error=f"{type(exc).__name__}: {exc}")
        return row
    row["sim_seconds"] = time.perf_counter() - t0
    reach = contact_reach(rec)
    if reach is not None:
        row["contact_reach"] = reach
        row["effect_present"] = bool(max(reach.values()) > 1.0)
    row["effect_parameters"] = rec["effect_parameters"]
    row["truth"] = rec["truth"]
    row["samples"] = sum(int(s["t"].size) for s in rec["stages"].values())
    baseline = model_of(rec["baseline"]) if "baseline" in rec else "paper"
    row["baseline"] = "paper" if baseline == "paper" else "truth without the term"
    t1 = time.perf_counter()
    try:
        run = to_run(rec)
        dg = diagnose(run, baseline=baseline)
        out = dg.to_dict()
    except UserFacingError as exc:   # `shakerlab diagnose` refuses (exit 2, the message; under --json an object)
        row.update(status="refused", error=f"{type(exc).__name__}: {exc}"[:400], seconds=time.perf_counter() - t1)
        return _block_scores(row)
    except Exception as exc:  # noqa: BLE001 - a raised diagnosis is a row
        row.update(status="failed", error=f"{type(exc).__name__}: {exc}"[:400],
                   trace=traceback.format_exc(limit=4)[-800:], seconds=time.perf_counter() - t1)
        return _block_scores(row)
    row["seconds"] = time.perf_counter() - t1
    ids = [m["id"] for m in out["missing_physics"]]
    amb = _ambiguous_ids(out)
    first = "ambiguous" if amb else (ids[0] if ids else "none")
    true = d["effect"]
    fb, fa = out["fit_before"], out["fit_after"]
    given_key = next((k for k in fb if "held" in k and "given" in k), None)
    held_stages = [s for s in fb["nrmse"] if s.startswith("validation")]
    given = fb[given_key] if given_key else (fb["nrmse"][held_stages[0]] if len(held_stages) == 1 else None)
    lacks = baseline_lacks(dg.baseline.baseline, rec["truth"])
    row.update(status="ok", named=ids, ambiguous=amb, first=first, baseline_lacks=lacks,
               names_a_lacking_term=true == "none" and first in lacks,
               right=(first == true) if true != "none" and not amb else (bool(amb) and true in amb) if amb
               else first == "none",
               held_out={"as_given": given, "null": fb.get("refit_held_out_nrmse", fb.get("held_out_nrmse")),
                         "after": fa.get("held_out_nrmse")},
               parameters={m["id"]: {k: v["value"] for k, v in m["parameters"].items()}
                           for m in out["missing_physics"]},
               result=out["result"], unexplained=bool(out.get("unexplained_mismatch")),
               partly=out.get("partly_explained"), baseline_warnings=out.get("baseline_warnings", []),
               baseline_fallback=bool(out.get("baseline_note")),
               baseline_loop_as_friction=out.get("baseline_loop_as_friction"),
               candidates=[{k: c[k] for k in CANDIDATE_KEYS if k in c} for c in out.get("candidates_tested", [])])
    if baseline == "paper":
        # how far the reconstructed baseline's c and K = k + alpha are from the truth's (relative): what a
        # linear step on a noisy linear stage, or its stand-in, left the diagnosis to work from
        bm, tr = dg.baseline.baseline, rec["truth"]
        row["baseline_cK_error"] = {"c_m": abs(bm.c_m / tr["c_m"] - 1),
                                    "K_m": abs(bm.K_m / (tr["k_m"] + tr["alpha_m"]) - 1)}
    size = true_size(rec, out)
    if size is not None:
        row["truth_size"] = size
    row.update(truth_figures(rec, run, dg.baseline.baseline, dg.reference))
    h = row["held_out"]
    if ids:
        row["after_beats_both"] = bool(h["after"] is not None and h["null"] is not None and h["as_given"] is not None
                                       and h["after"] < h["null"] and h["after"] < h["as_given"])
    return _block_scores(row)


def _block_scores(row: dict) -> dict:
    """A pair row's and a weak-linear row's own scores (:func:`score_pair`, :func:`score_weak_linear`)
    added to the row; a pair row's ``right`` is its ``right_first``."""
    if row.get("block") == "pairs":
        row.update(score_pair(row))
        row["right"] = row["right_first"]
    elif row.get("block") == "weak_linear":
        row.update(score_weak_linear(row))
    return row


def report(rows: list[dict]) -> list[str]:
    ok = [r for r in rows if r["status"] == "ok"]
    cols = sorted({r["first"] for r in ok} - {"none", "ambiguous"})
    cols = cols + ["none", "ambiguous", "error"]
    trues = list(dict.fromkeys(effect_cycle() + list(CORNER_EFFECTS)))
    out = ["| true \\ named first | n | " + " | ".join(cols) + " | right first |",
           "| --- | --- | " + " | ".join("---" for _ in cols) + " | --- |"]
    for t in trues:
        rs = [r for r in rows if r["effect"] == t]
        if not rs:
            continue
        c = collections.Counter("error" if r["status"] != "ok" else r["first"] for r in rs)
        right = sum(r.get("right", False) for r in rs)
        out.append(f"| {t} | {len(rs)} | " + " | ".join(str(c.get(k, 0) or ".") for k in cols)
                   + f" | {right}/{len(rs)} |")
    n = len(rows)
    right = sum(r.get("right", False) for r in rows)
    eff = [r for r in rows if r["effect"] != "none"]
    clean = [r for r in rows if r["effect"] == "none"]
    fa = sum(r["status"] == "ok" and r["first"] != "none" for r in clean)
    lacking = [r for r in clean if r.get("names_a_lacking_term")]
    lack, lack_ids = len(lacking), ", ".join(f"#{r['index']} {r['first']}" for r in lacking)
    named = [r for r in ok if r["named"]]
    beats = sum(r["after_beats_both"] for r in named)
    errs = sum(r["status"] != "ok" for r in rows)
    out += ["",
            f"right first (or in an ambiguous pair that holds it): {right}/{n} = {right / max(n, 1):.1%} "
            f"(effects only: {sum(r.get('right', False) for r in eff)}/{len(eff)})",
            f"false alarms on clean recordings: {fa}/{len(clean)} = {fa / max(len(clean), 1):.1%}"
            + (f" (of which {lack} name a true term the reconstructed baseline lacks: {lack_ids})" if lack else ""),
            f"named cases with held-out NRMSE after < both the baseline as given and the null model: "
            f"{beats}/{len(named)} = {beats / max(len(named), 1):.1%}",
            f"diagnose raised / generator failed: {errs}/{n}"]
    short = [r for r in eff if r["status"] == "ok" and r.get("baseline_lacks")]
    if short:
        # a record that lacks two things (the concealed effect, and a true term its reconstructed
        # baseline missed): where the lacking term is named first and the effect after it, with no
        # other name, every name is true; still a miss in the strict count above
        after = [r for r in short if not r.get("right") and r["first"] in r["baseline_lacks"]
                 and r["effect"] in r["named"] and set(r["named"]) <= set(r["baseline_lacks"]) | {r["effect"]}]
        out.append(f"effect recordings whose baseline lacks a true term: {len(short)}, right first on "
                   f"{sum(r.get('right', False) for r in short)}; the lacking term first and the effect after it "
                   f"(every name true): {len(after)}" + (f" ({', '.join('#%d' % r['index'] for r in after)})" if after else ""))
    fallback = [r for r in rows if r.get("status") == "ok" and r.get("baseline_fallback")]
    if fallback:
        # the paper baseline was one of reconstruct's simpler models (diagnose's baseline_note)
        out.append(f"recordings whose paper baseline is a reconstruct fallback (a simpler model): {len(fallback)}, "
                   f"right first on {sum(r.get('right', False) for r in fallback)} ("
                   + ", ".join(f"#{r['index']} {r['effect']}: {r['first']}" for r in fallback) + ")")
    missed = [r for r in eff if r["status"] == "ok" and r["first"] == "none"]
    flagged = [r for r in missed if r.get("unexplained")]
    clean_flag = [r for r in clean if r["status"] == "ok" and r["first"] == "none" and r.get("unexplained")]
    absent = [r for r in eff if r.get("effect_present") is False]
    if absent:
        present = [r for r in eff if r.get("effect_present") is not False]
        which = ", ".join(f"#{r['index']} {r['protocol']}: {r['first']}" for r in absent)
        out.append(f"contact recordings whose motion never reaches the gap (no contact in the record): {len(absent)} "
                   f"({which}); right first on the effect recordings that hold their effect: "
                   f"{sum(r.get('right', False) for r in present)}/{len(present)}")
    judged = [r for r in eff if r["status"] == "ok" and isinstance(r.get("oracle"), dict) and "significant" in r["oracle"]]
    if judged:
        # the rule applied now to the oracle's stored figures, so that rows diagnosed under an older
        # rule are judged by the current one (the figures themselves do not depend on the rule)
        shows = [r for r in judged if _passes_now(r["oracle"])]
        hidden = [r for r in judged if r not in shows]
        out.append(f"the truth itself put to the rule (oracle), on {len(judged)} effect recordings: it passes on "
                   f"{len(shows)}; right first on those {sum(r.get('right', False) for r in shows)}/{len(shows)}"
                   + (f" = {sum(r.get('right', False) for r in shows) / len(shows):.1%}" if shows else "")
                   + f"; on the {len(hidden)} where it does not, right first {sum(r.get('right', False) for r in hidden)}"
                   f"/{len(hidden)}")
        if hidden:
            # why the truth fails: its effect hardly shows (the held-out NRMSE falls by less than the rule's
            # relative minimum) or it shows but the rule's other margins (gain over the noise, BIC) refuse it
            faint = [r for r in hidden if (r["oracle"].get("relative_gain") or 0.0) < DEFAULT_RULE.min_rel_gain]
            held = [r for r in hidden if r not in faint]
            out.append(f"  of those {len(hidden)}: {len(faint)} where the truth lowers the held-out NRMSE by less "
                       f"than {DEFAULT_RULE.min_rel_gain:.0%} (" + ", ".join(f"#{r['index']}" for r in faint)
                       + f"); {len(held)} where it lowers it more but fails the other margins ("
                       + ", ".join(f"#{r['index']} gain {r['oracle'].get('gain_over_noise', float('nan')):.2f} noise var, "
                                   f"dBIC {r['oracle'].get('dbic', float('nan')):.0f}" for r in held) + ")")
        missed_shown = [r for r in shows if not r.get("right")]
        if missed_shown:
            # where the truth passes and the diagnosis missed: does the effect act on the fitting
            # samples at all (effect_signature; a row without it was diagnosed before the figure)
            def sig(r):
                """(fitting, held-out) signature over the noise, or None without both figures."""
                sg = r.get("effect_signature") or {}
                f, h = sg.get("fit_over_noise"), sg.get("held_over_noise")
                return None if f is None or h is None else (f, h)
            known = [r for r in missed_shown if sig(r)]
            unseen = [r for r in known if sig(r)[0] < FIT_SIGNATURE_SHARE * sig(r)[1]]
            # the effect alone can cut the held-out NRMSE by the rule's smallest relative cut g only if its
            # signature there is at least sqrt(1 / (1 - g)^2 - 1) of the noise (the reference's error
            # being the noise and the effect at best); below it the truth passes on its baseline's terms
            g = rank.smallest_relative_cut()
            s_min = math.sqrt(1.0 / (1.0 - g) ** 2 - 1.0)
            unheld = [r for r in known if sig(r)[1] < s_min]
            out.append(f"  missed where the truth passes: {len(missed_shown)}, {len(known)} with the effect's signature ("
                       + "; ".join(f"#{r['index']} {r['effect']} {r['protocol']}: signature {sig(r)[0]:.3g} x noise "
                                   f"fitting, {sig(r)[1]:.3g} held out" for r in known)
                       + f"); of those {len(unseen)} whose effect acts on the fitting samples at under "
                       f"{FIT_SIGNATURE_SHARE:.0%} of its held-out size (no fit to those samples can find it)"
                       + (f" ({', '.join('#%d' % r['index'] for r in unseen)})" if unseen else "")
                       + f", and {len(unheld)} whose effect acts on the held-out samples at under {s_min:.2f} x the "
                       f"noise (too little to cut the held-out NRMSE by {g:.0%}: the truth passes there on its "
                       f"baseline's terms)" + (f" ({', '.join('#%d' % r['index'] for r in unheld)})" if unheld else ""))
    sized = [r for r in eff if r["status"] == "ok" and r.get("truth_size")]
    if sized:
        # the diagnosis's own detection limit for the true candidate against the concealed effect's size
        above = [r for r in sized if abs(r["truth_size"]["truth"]) >= r["truth_size"]["limit"]]
        below = [r for r in sized if r not in above]
        out.append(f"the true candidate's detection limit (candidates_tested[].detection_limit) against the "
                   f"concealed size, on {len(sized)} effect recordings: above its limit {len(above)}, right first "
                   f"{sum(r.get('right', False) for r in above)}/{len(above)}; below it {len(below)}, right first "
                   f"{sum(r.get('right', False) for r in below)}/{len(below)}"
                   + (" (" + ", ".join(f"#{r['index']} {abs(r['truth_size']['truth']) / r['truth_size']['limit']:.2f}"
                                       f" x the limit" for r in below) + ")" if below else ""))
    out.append(f"effects named nothing: {len(missed)}, of which {len(flagged)} flagged as an unexplained mismatch; "
               f"clean recordings named nothing but flagged: {len(clean_flag)}/{len(clean)}")
    out += _times(rows)
    by_p = collections.defaultdict(list)
    for r in rows:
        by_p[r["protocol"]].append(r.get("right", False))
    out.append("right first by protocol: " + ", ".join(f"{p} {sum(v)}/{len(v)}" for p, v in sorted(by_p.items())))
    bands = [(lo, lo + 5.0) for lo in range(40, 80, 5)]
    snr = [(r.get("snr"), r.get("right", False)) for r in rows if r.get("snr") is not None]
    by_snr = [[ok for v, ok in snr if lo <= v < hi or (hi == 80.0 and v == 80.0)] for lo, hi in bands]
    out.append("right first by SNR: " + ", ".join(f"{lo:g}-{hi:g} dB {sum(v)}/{len(v)}"
                                                 for (lo, hi), v in zip(bands, by_snr) if v))
    return out


def report_pairs(rows: list[dict]) -> list[str]:
    """The table of pair rows (:func:`score_pair`): per pair, what was named first, how often one of
    the two came first and how often both were named."""
    for r in rows:
        if "right_first" not in r:       # a row stored without its scores
            r.update(score_pair(r))
    ok = [r for r in rows if r["status"] == "ok"]
    cols = sorted({r["first"] for r in ok} - {"none", "ambiguous"}) + ["none", "ambiguous", "error"]
    out = ["| pair concealed \\ named first | n | " + " | ".join(cols) + " | one of the two first | both named |",
           "| --- | --- | " + " | ".join("---" for _ in cols) + " | --- | --- |"]
    pairs = list(dict.fromkeys([" + ".join(p) for p in PAIRS] + [" + ".join(r["pair"]) for r in rows]))
    for p in pairs:
        rs = [r for r in rows if " + ".join(r["pair"]) == p]
        if not rs:
            continue
        c = collections.Counter("error" if r["status"] != "ok" else r["first"] for r in rs)
        out.append(f"| {p} | {len(rs)} | " + " | ".join(str(c.get(k, 0) or ".") for k in cols)
                   + f" | {sum(r['right_first'] for r in rs)}/{len(rs)} | {sum(r['both'] for r in rs)}/{len(rs)} |")
    n = len(rows)
    first, both = sum(r["right_first"] for r in rows), sum(r["both"] for r in rows)
    wrong = [r for r in ok if r["wrong_names"]]
    amb = [r for r in ok if r["right_first"] and r["first"] == "ambiguous"]
    lacking = [r for r in wrong if set(r["wrong_names"]) <= set(r.get("baseline_lacks") or [])]
    named = [r for r in ok if r["named"]]
    beats = sum(r.get("after_beats_both", False) for r in named)
    refused = [r for r in rows if r["status"] == "refused"]
    raised = [r for r in rows if r["status"] not in ("ok", "refused")]
    out += ["",
            f"one of the two concealed effects named first: {first}/{n} = {first / max(n, 1):.1%}"
            + (f" (of which {len(amb)} an ambiguous answer that holds one: "
               + ", ".join(f"#{r['index']} {' or '.join(r['ambiguous'])}" for r in amb) + ")" if amb else "")
            + f"; both named: {both}/{n} = {both / max(n, 1):.1%}",
            f"a name that neither effect is: {len(wrong)}/{n}"
            + (" (" + ", ".join(f"#{r['index']} {'+'.join(r['wrong_names'])}" for r in wrong) + ")" if wrong else "")
            + (f"; of those, {len(lacking)} only a true term the reconstructed baseline lacks ("
               + ", ".join(f"#{r['index']}" for r in lacking) + ")" if lacking else ""),
            f"named cases with held-out NRMSE after < both the baseline as given and the null model: "
            f"{beats}/{len(named)}",
            f"refused: {len(refused)}/{n}" + "".join(f"; #{r['index']}: {r['error']}" for r in refused),
            f"diagnose raised / generator failed: {len(raised)}/{n}"
            + "".join(f"; #{r['index']}: {r.get('error', '')[:160]}" for r in raised)]
    contacts = [r for r in ok if r.get("contact_reach")]
    if contacts:
        # the gap is placed on the nonlinear stage's peaks: a validation stage that does not reach it
        # holds no contact, and the diagnosis judges on held-out samples
        out.append("contact pairs, the largest motion towards the stop over the gap per stage: " + "; ".join(
            f"#{r['index']} " + ", ".join(f"{k} {v:.2f}" for k, v in r["contact_reach"].items()) for r in contacts))
    out += _times(rows)
    return out


def report_weak_linear(rows: list[dict]) -> list[str]:
    """The usual table of weak-linear rows (:func:`report`), then whether each was diagnosed at all and
    whether the answer said that the linear stage was too noisy (:func:`score_weak_linear`)."""
    for r in rows:
        if "diagnosed" not in r:         # a row stored without its scores
            r.update(score_weak_linear(r))
    n = len(rows)
    done = [r for r in rows if r["diagnosed"]]
    refused = [r for r in rows if r["status"] == "refused"]
    raised = [r for r in rows if r["status"] not in ("ok", "refused")]
    judged = [r for r in done if r["linear_reported_noisy"] is not None]
    said = [r for r in judged if r["linear_reported_noisy"]]
    out = report(rows) + [
        f"linear stage at {min(r['linear_snr'] for r in rows):g}-{max(r['linear_snr'] for r in rows):g} dB: "
        f"diagnosed {len(done)}/{n}, refused {len(refused)}/{n}, raised {len(raised)}/{n}",
        f"the answer says the linear stage was too noisy: {len(said)}/{len(judged)} of the diagnosed rows whose "
        f"baseline was reconstructed from the run ({len(done) - len(judged)} with a given baseline: no linear step)"
        + (" (not said on " + ", ".join(f"#{r['index']} at {r['linear_snr']:g} dB" for r in judged if r not in said)
           + ")" if len(said) < len(judged) else "")]
    errs = [r for r in done if r.get("baseline_cK_error")]
    if errs:
        out.append("the reconstructed baseline's c and K against the truth's: " + "; ".join(
            f"#{r['index']} ({r['linear_snr']:g} dB{', said too noisy' if r['linear_reported_noisy'] else ''}) "
            f"c {r['baseline_cK_error']['c_m']:.1%}, K {r['baseline_cK_error']['K_m']:.1%}" for r in errs))
    out += [f"refused #{r['index']} ({r['effect']}, linear stage {r['linear_snr']:g} dB): {r['error']}"
            for r in refused]
    out += [f"raised #{r['index']} ({r['effect']}): {r.get('error', '')[:200]}" for r in raised]
    return out


def _times(rows: list[dict]) -> list[str]:
    secs = [r["seconds"] for r in rows if "seconds" in r]
    sims = [r["sim_seconds"] for r in rows if "sim_seconds" in r]
    if not secs:
        return []
    return [f"time per recording: generate median {np.median(sims):.1f} s (max {max(sims):.1f}), diagnose "
            f"median {np.median(secs):.1f} s (max {max(secs):.1f})"]


BLOCK_TITLES = {"random": "the random block", "pairs": "two effects concealed together",
                "weak_linear": "a linear stage at 0-10 dB SNR"}


def report_apart(rows: list[dict]) -> list[str]:
    """The report of each block's rows apart (:func:`block_of`; a corner's rows per corner): figures
    on one block do not transfer to another, and a pair row or a weak-linear row never enters the
    random block's confusion table."""
    groups = {}
    for r in rows:
        b = block_of(r)
        groups.setdefault((b, r.get("corner") if b == "corner" else None), []).append(r)
    order = ("random", "corner", "pairs", "weak_linear")
    out = []
    for key in sorted(groups, key=lambda k: (order.index(k[0]) if k[0] in order else len(order), str(k[1]))):
        rs = groups[key]
        block, corner = key
        if len(groups) > 1 or block != "random":
            title = f"corner {corner}" if block == "corner" else BLOCK_TITLES.get(block, block)
            out += ["", f"== {title}: {len(rs)} rows =="]
        out += (report_pairs(rs) if block == "pairs" else report_weak_linear(rs) if block == "weak_linear"
                else report(rs))
    return out


def _passes_now(o: dict) -> bool:
    """The current significance rule on stored held-out figures (an oracle's, a candidate's); the
    stored verdict where a figure is missing."""
    if not all(k in o for k in ("dbic", "explained", "gain_over_noise", "relative_gain")):
        return bool(o.get("significant"))
    return rank.passes(o["dbic"], o["explained"], o["gain_over_noise"], o["relative_gain"], o.get("blocks_improved"))


def rescore(rows: list[dict]) -> list[str]:
    """The diagnosis's current rule (rank.passes) put to the stored figures of every candidate of
    ``rows``: the verdicts that change, and the rows that must be run again to know their new answer.
    A candidate refused as implausible stays refused. A row with a changed verdict may answer
    differently beyond that verdict: a significant candidate gets a nested null, and a pair is tried
    only when none is significant alone. A candidate whose score from before its nested null is
    stored (``before_nested_null``) is judged on that too; rows stored without it cannot show such
    a change."""
    changed, rerun, judged, unknown = [], [], 0, 0
    for r in rows:
        if r.get("status") != "ok":
            continue
        flips = []
        for c in r.get("candidates", []):
            if "dbic" not in c:
                continue
            judged += 1
            for label, fig in (("", c), (" before its nested null", c.get("before_nested_null"))):
                if not fig:
                    continue
                # an implausible candidate is refused after its score (its nested null, fitted on
                # the score alone, is judged without that)
                now = _passes_now(fig) and (bool(label) or not c.get("implausible"))
                if now != bool(fig["significant"]):
                    flips.append(f"{c['id']}{label} {'now significant' if now else 'no longer significant'} "
                                 f"(explained {fig['explained']:.3f}, gain {fig['gain_over_noise']:.3g} noise "
                                 f"variances, {fig['relative_gain']:.1%}, pieces {fig.get('blocks_improved')})")
            if c.get("compared_with_nested_null") and not c.get("before_nested_null"):
                unknown += 1
        if flips:
            rerun.append(r["index"])
            changed += [f"  #{r['index']} {r['effect']} ({r['protocol']}, first {r.get('first')}): {f}" for f in flips]
    out = [f"the current rule on {judged} stored candidates of {len(rows)} rows: "
           f"{len(changed)} verdict(s) change, on {len(rerun)} row(s)"]
    out += changed
    if rerun:
        out.append("run again (--rows): " + " ".join(str(i) for i in rerun))
    if unknown:
        out.append(f"{unknown} candidate(s) scored against a nested null without their earlier score stored "
                   "(rows saved before the nested null's score was stored): a change there shows only in a rerun")
    return out


def oracle_of_stored(row: dict) -> dict:
    """``row`` (a stored row) with its oracle, the recording generated again from its index. A row
    whose recording no longer comes out the same (another sample count: the generator's protocol
    changed since) gets ``oracle = {"stale": ...}``."""
    warnings.filterwarnings("ignore")
    row = dict(row)
    if row.get("status") != "ok" or row["effect"] == "none":
        return row
    rec = recording_of(row)
    n = sum(int(s["t"].size) for s in rec["stages"].values())
    if n != row.get("samples"):
        row["oracle"] = {"stale": f"the recording has {n} samples now, {row.get('samples')} when diagnosed"}
        return row
    h = row["held_out"]
    ref = min(v for v in (h["as_given"], h["null"]) if v is not None)
    tm = true_model(rec)
    kept = row.get("oracle")
    # an oracle the row got when it was diagnosed (against the reference's own residual, so with
    # its held-out pieces) is kept: one from the stored figures alone cannot count the pieces
    kept = kept if isinstance(kept, dict) and kept.get("blocks_improved") is not None else None
    row.update(truth_figures(rec, to_run(rec), tm[0].baseline if tm else None, ref, kept))
    return row

"""`python bench/recon_accuracy.py --stress`: reconstruction on recordings of the independent
generator (issue 18). See recon_accuracy.py's docstring for the design; this module holds it."""
from __future__ import annotations

import faulthandler
import json
import math
import multiprocessing as mp
import os
import sys
import time
import traceback
import warnings

import numpy as np

from recon import ReconSettings, reconstruct
from recon.estimator.two_stage import two_stage_polish
from recon.output_error.polish import polish
from recon.library import monomials
from recon.testing import independent as ind
from recon.testing.runs import model_of, score, to_run
from recon.testing.stress import stress_system

SNRS = (80.0, 60.0, 50.0, 40.0)
STUCK_S = 240.0


# a draw is "identifiable" when its nonlinear stage drives the Bouc-Wen loop past its knee
# (lambda * max|y| >= KNEE) and every true fn term's force at the stage's peak motion is at least
# TERM_SHARE of the elastic force K max|y|: otherwise the record itself cannot separate k from
# alpha, or hold the term (judged on the clean recording and the truth, not on the estimate)
KNEE = 1.0
TERM_SHARE = 0.01


def identifiability(rec: dict) -> dict:
    st = rec["stages"]["nonlinear"]
    y = np.asarray(st["x_tip"], float) - np.asarray(st["x_base"], float) if "x_tip" in st else np.asarray(st["x"], float)
    dt = float(st["t"][1] - st["t"][0])
    ymax = float(np.max(np.abs(y)))
    vmax = float(np.max(np.abs(np.gradient(y, dt))))
    tr = rec["truth"]
    lam = tr["gamma"] + tr["delta"]
    K = tr["k_m"] + tr["alpha_m"]
    share = {}
    for name, c in tr["fn_m"].items():
        p, r = monomials.parse(name)
        share[name] = abs(c) * ymax ** p * vmax ** r / (K * ymax)
    out = {"lambda_ymax": lam * ymax, "term_share": share}
    out["identifiable"] = bool(out["lambda_ymax"] >= KNEE and all(v >= TERM_SHARE for v in share.values()))
    return out


def run_seed(task) -> list[dict]:
    """Every SNR of one seed: simulate once, add noise (noise seed = seed + the task's noise offset,
    default 0), reconstruct, score."""
    seed, snrs, protocols, quantity, *more = task if len(task) > 3 else (*task, "displacement")
    noise_seed = seed + (more[0] if more else 0)
    warnings.filterwarnings("ignore")
    system, protocol, fs = stress_system(seed, protocols)
    t0 = time.perf_counter()
    try:
        rec = ind.simulate(system, protocol, fs, seed=seed)
    except Exception as exc:  # noqa: BLE001 - a generator failure is a row, not a crash
        return [{"seed": seed, "snr": snr, "protocol": protocol, "fs": fs, "system": system,
                 "status": "generator failed", "error": f"{type(exc).__name__}: {exc}"} for snr in snrs]
    t_sim = time.perf_counter() - t0
    ident = identifiability(rec)
    n_samples = {k: int(v["t"].size) for k, v in rec["stages"].items()}
    rows = []
    for snr in snrs:
        row = {"seed": seed, "noise_seed": noise_seed, "snr": snr, "protocol": protocol, "fs": fs, "system": system,
               **({"quantity": quantity} if quantity != "displacement" else {}),
               "truth": rec["truth"], "samples": n_samples, "sim_seconds": t_sim,
               "identifiability": ident}
        run = to_run(ind.add_noise(rec, snr, noise_seed, quantity=quantity))
        t1 = time.perf_counter()
        # a reconstruct that runs for minutes: dump where it is (stderr), once
        faulthandler.dump_traceback_later(STUCK_S, exit=False, file=sys.stderr)
        print(f"  seed {seed} {snr:g} dB: reconstruct ...", file=sys.stderr, flush=True)
        try:
            res = reconstruct(run, ReconSettings())
        except Exception as exc:  # noqa: BLE001
            faulthandler.cancel_dump_traceback_later()
            row.update(status="failed", error=f"{type(exc).__name__}: {exc}"[:400],
                       trace=traceback.format_exc(limit=3)[-800:], seconds=time.perf_counter() - t1)
            rows.append(row)
            continue
        faulthandler.cancel_dump_traceback_later()
        row["seconds"] = time.perf_counter() - t1
        print(f"  seed {seed} {snr:g} dB: {row['seconds']:.1f} s", file=sys.stderr, flush=True)
        sc = score(res.model, rec["truth"])
        val = res.validation.get("nrmse", float("nan"))
        if not (isinstance(val, float) and math.isfinite(val)):
            sc["inadmissible"].append(f"validation simulation not finite (NRMSE {val})")
        row.update(status="inadmissible" if sc["inadmissible"] else "ok", result=res.model.to_dict()["parameters"],
                   validation_nrmse=val, form=res.settings.form,
                   passes=res.hysteresis_info.get("passes_compared"), pass_kept=res.hysteresis_info.get("pass"),
                   two_stage=two_stage_summary(res.model), restart=restart_summary(res.model),
                   **sc)
        if not meets_target(row):
            row["record_limit"] = record_limit(run, rec["truth"])
        rows.append(row)
    return rows


def two_stage_summary(model) -> dict:
    """The two-stage fit's figures from the model's provenance: whether it was kept, the joint mean
    square per sample in noise variances, and whether a restart was kept."""
    rec = (model.provenance.get("output_error_polish") or {}).get("two_stage") or {}
    restart = rec.get("restart") or {}
    return {"applied": rec.get("applied"), "mean_square": restart.get("mean_square_noise_variances"),
            "restart_applied": restart.get("applied"), "dropped": (rec.get("terms") or {}).get("dropped"),
            "joint_gain": rec.get("joint_gain_noise_variances"), "floor": restart.get("floor_noise_variances")}


def restart_summary(model) -> dict:
    """The nonlinear stage's floor test and generic restart from the model's provenance: the
    polished cost, the cost past the start's transient and the noise floor (NRMSE), whether the
    generic restarts ran and whether one was kept."""
    pol = model.provenance.get("output_error_polish") or {}
    gr = pol.get("generic_restart")
    return {**(pol.get("floor_test") or {}), "ran": gr is not None, "applied": bool(gr and gr.get("applied"))}


def meets_target(row: dict) -> bool:
    """Issue 18's target for one run: exact terms and every parameter within 2 % at 60 dB and above,
    within 5 % below."""
    return bool(row["status"] == "ok" and row.get("exact") and row["worst"] <= (0.02 if row["snr"] >= 60 else 0.05))


def record_limit(run, truth: dict) -> dict:
    """What the record itself allows: the output-error fits of reconstruct's polish started at the
    truth, with the true terms: the nonlinear stage (the same start-state rule), then both stages
    together as reconstruct's two-stage polish fits and keeps them. Its error is the part of a miss
    that no start or term selection can remove (noise on one tone per stage); a reconstruction that
    misses by more stopped short of the record's optimum."""
    truth_model = model_of(truth)
    st = run.stage("nonlinear")
    try:
        m, info = polish(truth_model, [truth_model.fit_item(st)], max_nfev=200)
        alone = score(m, truth)
        m2 = two_stage_polish(m, run, ReconSettings())
    except Exception as exc:  # noqa: BLE001 - a row, not a crash
        return {"failed": f"{type(exc).__name__}: {exc}"[:200]}
    sc = score(m2, truth)
    return {"worst": sc["worst"], "worst_param": sc["worst_param"], "cost_truth": info["nrmse_before"],
            "cost": info["nrmse_after"] if info["applied"] else info["nrmse_before"],
            "two_stage_applied": m2 is not m,
            "nonlinear_stage_only": {"worst": alone["worst"], "worst_param": alone["worst_param"]}}


def limited(row: dict) -> bool:
    """A miss the record explains: the truth-started fit misses the same target."""
    lim = row.get("record_limit") or {}
    return "worst" in lim and lim["worst"] > (0.02 if row["snr"] >= 60 else 0.05)


def table(rows: list[dict], snrs) -> list[str]:
    out = ["| SNR dB | runs | exact terms | median worst err % | p95 worst err % | exact and <= 2 % | "
           "exact and <= 5 % | inadmissible | failed | misses the record explains | median recon s |",
           "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    for snr in snrs:
        rs = [r for r in rows if r["snr"] == snr]
        if not rs:
            continue
        n = len(rs)
        ok = [r for r in rs if r["status"] in ("ok", "inadmissible")]
        # a failed or inadmissible run counts as a worst error of infinity in the percentiles
        worst = np.array([100 * r["worst"] if r["status"] == "ok" else np.inf for r in rs])
        exact = sum(r.get("exact", False) for r in ok)
        w2 = sum(r["status"] == "ok" and r["exact"] and r["worst"] <= 0.02 for r in rs)
        w5 = sum(r["status"] == "ok" and r["exact"] and r["worst"] <= 0.05 for r in rs)
        inad = sum(r["status"] == "inadmissible" for r in rs)
        fail = sum(r["status"] in ("failed", "generator failed") for r in rs)
        secs = [r["seconds"] for r in rs if "seconds" in r]
        misses = [r for r in rs if not meets_target(r)]
        explained = sum(limited(r) for r in misses)

        def pct(q):
            v = np.percentile(worst, q, method="higher")
            return "inf" if not np.isfinite(v) else f"{v:.3g}"
        out.append(f"| {snr:g} | {n} | {exact / n:.0%} ({exact}) | {pct(50)} | {pct(95)} | {w2 / n:.0%} ({w2}) | "
                   f"{w5 / n:.0%} ({w5}) | {inad / n:.0%} ({inad}) | {fail / n:.0%} ({fail}) | {explained} of {len(misses)} | "
                   f"{np.median(secs) if secs else float('nan'):.1f} |")
    return out


def worst_draws(rows: list[dict], k: int = 15) -> list[str]:
    # issue 18's targets: exact terms and within 2 % at 60 dB and above, within 5 % below
    bad = [r for r in rows if r["status"] != "ok" or not r.get("exact")
           or r.get("worst", 0) > (0.02 if r["snr"] >= 60 else 0.05)]
    bad.sort(key=lambda r: (r["status"] == "ok", -(r.get("worst") or 0)))
    out = []
    for r in bad[:k]:
        what = r.get("error") or "; ".join(r.get("inadmissible") or []) or (
            f"worst {100 * r['worst']:.3g} % ({r['worst_param']}), spurious {r['spurious']}, missed {r['missed']}")
        idf = r.get("identifiability", {})
        tag = (f" lambda*Y {idf['lambda_ymax']:.2g}" + ("" if idf.get("identifiable") else " (not identifiable)")) if idf else ""
        lim = r.get("record_limit") or {}
        if "worst" in lim:
            what += f"; truth-started fit {100 * lim['worst']:.3g} % ({lim['worst_param']})"
        out.append(f"seed {r['seed']} snr {r['snr']:g} {r['protocol']} fs {r['fs']:g} f_n {r['system']['f_n']:.3g}{tag} "
                   f"[{r['status']}] {what}")
    return out


def main(a) -> int:
    snrs = [float(s) for s in a.snr.split(",")] if a.snr else list(SNRS)
    protocols = tuple(a.protocols.split(","))
    if a.from_jsonl:
        return report(stored_rows(a.from_jsonl, snrs), snrs, protocols, "stored rows: " + ", ".join(a.from_jsonl),
                      getattr(a, "against", None))
    seeds = [int(v) for v in a.seed_list.split(",")] if a.seed_list else \
        list(range(a.first_seed, a.first_seed + (a.seeds or 50)))
    n = len(seeds)
    tasks = [(s, snrs, protocols, getattr(a, "quantity", "displacement"), getattr(a, "noise_offset", 0))
             for s in seeds]
    rows = []
    t0 = time.perf_counter()
    if a.jsonl and os.path.exists(a.jsonl):     # stored rows are never overwritten
        print(f"{a.jsonl} exists: give a new file for the rows (--from-jsonl joins files)", file=sys.stderr)
        return 2
    out = open(a.jsonl, "x") if a.jsonl else None
    workers = max(1, min(a.workers, 2))
    pool = mp.get_context("fork").Pool(workers) if workers > 1 else None
    it = pool.imap_unordered(run_seed, tasks) if pool else map(run_seed, tasks)
    for k, rs in enumerate(it, 1):
        rows += rs
        if out:
            for r in rs:
                out.write(json.dumps(r, default=float) + "\n")
            out.flush()
        r0 = rs[0]
        print(f"[{k}/{n}] seed {r0['seed']} {r0['protocol']} fs {r0['fs']:g}: sim {r0.get('sim_seconds', 0):.1f} s, "
              + ", ".join(f"{r['snr']:g} dB {r['status']} "
                          + (f"{100 * r['worst']:.3g} %" if 'worst' in r else '')
                          + f" ({r.get('seconds', 0):.1f} s)" for r in rs), flush=True)
    if pool:
        pool.close()
        pool.join()
    if out:
        out.close()
    wall = time.perf_counter() - t0
    return report(rows, snrs, protocols, f"seeds {seeds[0]}..{seeds[-1]} ({n}), {workers} worker(s), wall {wall:.0f} s",
                  getattr(a, "against", None))


def stored_rows(paths, snrs) -> list[dict]:
    """Rows of --jsonl files, the last one for each (seed, SNR) kept, at the SNRs asked for."""
    rows = {}
    for path in paths:
        with open(path) as f:
            for line in f:
                r = json.loads(line)
                if r["snr"] in snrs:
                    rows[(r["seed"], r["snr"])] = r
    return [rows[k] for k in sorted(rows)]


def parameter_change(a: dict, b: dict) -> float:
    """The largest relative difference between two rows' fitted parameters (inf where their terms
    differ or either row has none)."""
    ra, rb = a.get("result"), b.get("result")
    if not (isinstance(ra, dict) and isinstance(rb, dict)) or set(ra.get("fn_m", {})) != set(rb.get("fn_m", {})):
        return math.inf
    pa = {**{k: v for k, v in ra.items() if isinstance(v, (int, float))}, **ra.get("fn_m", {})}
    pb = {**{k: v for k, v in rb.items() if isinstance(v, (int, float))}, **rb.get("fn_m", {})}
    if set(pa) != set(pb):
        return math.inf
    return max((abs(pa[k] - pb[k]) / max(abs(pb[k]), 1e-300) if pa[k] != pb[k] else 0.0 for k in pa), default=0.0)


def compare(rows: list[dict], reference: list[dict], tol: float = 1e-6) -> list[str]:
    """Lines that say which rows answer as the stored ``reference`` rows (the same seed and SNR):
    the same terms and every parameter within ``tol`` (relative); each other row with its worst
    parameter error against the truth then and now."""
    ref = {(r["seed"], r["snr"]): r for r in reference}
    both = [(r, ref[(r["seed"], r["snr"])]) for r in rows if (r["seed"], r["snr"]) in ref]
    changed = [(r, o, parameter_change(r, o)) for r, o in both]
    changed = [c for c in changed if not c[2] <= tol]
    out = [f"\nagainst the stored rows: {len(both) - len(changed)} of {len(both)} the same (terms, and every "
           f"parameter within {tol:g}); {len(rows) - len(both)} not in them"]
    for r, o, d in sorted(changed, key=lambda c: (c[0]["seed"], -c[0]["snr"])):
        out.append(f"  seed {r['seed']} {r['snr']:g} dB {r.get('protocol', '')}: parameters moved {d:.3g}; worst "
                   f"{100 * o.get('worst', math.nan):.3g} % -> {100 * r.get('worst', math.nan):.3g} %, exact "
                   f"{o.get('exact')} -> {r.get('exact')}, status {o.get('status')} -> {r.get('status')}")
    return out


def report(rows: list[dict], snrs, protocols, what: str, against=None) -> int:
    print(f"\nindependent generator, protocols {', '.join(protocols)}, {what}")
    print("\n".join(table(rows, snrs)))
    ident = [r for r in rows if r.get("identifiability", {}).get("identifiable")]
    seeds_i = sorted({r["seed"] for r in ident})
    print(f"\nidentifiable draws only ({len(seeds_i)} of {len({r['seed'] for r in rows})} systems: the nonlinear stage "
          f"drives the loop past its knee, lambda max|y| >= {KNEE:g}, and every true fn term's force at the peak "
          f"motion is >= {TERM_SHARE:.0%} of K max|y|; judged on the truth and the clean record):")
    print("\n".join(table(ident, snrs)))
    print("\nworst draws (seed = system and noise seed; reproduce with --first-seed SEED --seeds 1 --snr SNR):")
    print("\n".join(worst_draws(rows)) or "none")
    if against:
        print("\n".join(compare(rows, stored_rows(against, snrs))))
    return 0

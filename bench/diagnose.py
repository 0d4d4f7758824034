"""Confusion table of the mismatch diagnosis over random effect strengths and seeds.

    python bench/diagnose.py            # 3 seeds per effect, strengths uniform in [0.5, 1.5]
    python bench/diagnose.py --quick    # 1 seed per effect, strength 1 (the "concealed" level)
    python bench/diagnose.py --strength 0.1 0.3 --snr 50   # weaker effects, noisier sensors
    python bench/diagnose.py --rig      # on the simulated rig's own physics (sim_backend, in-process)
    python bench/diagnose.py --stress --n 200 --workers 2 --jsonl diag.jsonl   # independent generator (issue 13)
    python bench/diagnose.py --stress --from-jsonl a.jsonl b.jsonl   # the table of saved rows, joined
    python bench/diagnose.py --stress --rows 6 45 54 --workers 2 --jsonl r.jsonl   # chosen recordings
    python bench/diagnose.py --stress --oracle-of a.jsonl --jsonl o.jsonl   # saved rows' oracle (below)
    python bench/diagnose.py --stress --corner --rows 0 1 2 --workers 2   # issue 76's corner, reported apart
    python bench/diagnose.py --stress --pairs --rows 0 1 2 --jsonl p.jsonl  # two effects concealed together
    python bench/diagnose.py --stress --weak-linear --rows 0 1 2 --jsonl w.jsonl   # a linear stage at 0-10 dB

--stress: recordings of recon/testing/independent.py (no code shared with recon): random
systems, protocols (paper, rig, sweep, multisine), sample rates, SNR and effect strengths,
each diagnosed as `shakerlab diagnose RUN.h5` does by default; confusion table, right-first
share, false alarms on clean recordings, held-out NRMSE after against the baseline as given
and the null model (bench/diagnose_stress.py). Each effect row also puts the recording's own
truth (its system with the effect, parameters as generated) to the rule a candidate must pass,
against the diagnosis's reference: where even the truth does not pass, the record does not show
the effect beyond what the baseline explains (the "oracle" line of the table). And it measures
where the effect acts ("effect_signature": the truth against the truth without the effect, over
the noise, on the fitting and on the held-out samples): a miss whose effect the fitting samples
do not show is one no fit could avoid.

Each recording (recon.testing.concealed: base excitation, 1 kHz, 3 x 4 s stages, 70 dB)
has one catalog effect concealed; the diagnosis runs blind against the truth's model without
the effect. Prints per effect: how often the right id ranks first, how often anything is
reported, the most frequent wrong first answer, the validation NRMSE of the baseline (as given),
of the baseline refitted and of the augmented model, and the time per diagnosis.
Clean recordings give the false-alarm rate.
"""
from __future__ import annotations

import argparse
import collections
import time

import numpy as np

from recon.testing.concealed import EFFECTS, concealed_run
from recon.diagnosis.diagnose import diagnose


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="1 seed per effect at strength 1")
    ap.add_argument("--seeds", type=int, default=3, help="recordings per effect (default 3)")
    ap.add_argument("--snr", type=float, default=70.0, help="SNR per channel [dB] (default 70)")
    ap.add_argument("--effects", nargs="*", default=None, help="subset of effects (default: all + clean)")
    ap.add_argument("--strength", nargs=2, type=float, default=(0.5, 1.5), metavar=("LO", "HI"),
                    help="effect strength drawn uniformly in [LO, HI] (1 = concealed level; default 0.5 1.5)")
    ap.add_argument("--rig", action="store_true",
                    help="recordings from sim_backend.physics in-process (shaker + amplifier, 10 kHz read at 1 kHz)")
    ap.add_argument("--stress", action="store_true", help="independent generator's stress table (issue 13)")
    ap.add_argument("--n", type=int, default=200, help="--stress: recordings (default 200)")
    ap.add_argument("--first", type=int, default=0, help="--stress: first recording index")
    ap.add_argument("--workers", type=int, default=1, help="--stress: worker processes (at most 2)")
    ap.add_argument("--jsonl", default=None, help="--stress: one JSON row per recording")
    ap.add_argument("--from-jsonl", nargs="+", default=None, metavar="JSONL",
                    help="--stress: print the table of rows saved by --jsonl (several files are joined; a "
                         "block's recording index seen twice keeps its last row) instead of running")
    ap.add_argument("--oracle-of", nargs="+", default=None, metavar="JSONL",
                    help="--stress: put the truth of each saved row's recording (generated again) to the "
                         "diagnosis's rule against that row's reference (a row's own oracle, counted on its "
                         "held-out pieces, is kept), and add the effect's signature; rows to --jsonl")
    ap.add_argument("--rescore", nargs="+", default=None, metavar="JSONL",
                    help="--stress: put the diagnosis's current rule to the stored candidate figures of these "
                         "rows and list the verdicts that change and the rows to run again (no diagnosis run)")
    ap.add_argument("--corner", action="store_true",
                    help="--stress: the recordings of issue 76's corner (recon.testing.stress.corner_draw: negative "
                         "delta with a hardening cubic, 5 kHz, sub-micron noise, validation above resonance, a "
                         "second mode above 3 f_n) instead of the random block; their rows carry 'corner'")
    ap.add_argument("--pairs", action="store_true",
                    help="--stress: two effects concealed together (recon.testing.stress.pair_draw: pairs in turn, "
                         "each at 0.5-1.5 of nominal, SNR 50-80 dB) instead of the random block; rows carry "
                         "block 'pairs' and are reported apart (one of the two first, both named)")
    ap.add_argument("--weak-linear", action="store_true",
                    help="--stress: the linear stage at 0-10 dB SNR, the others at 40-80 dB "
                         "(recon.testing.stress.weak_linear_draw) instead of the random block; rows carry block "
                         "'weak_linear' and are reported apart (diagnosed or refused, linear stage said too noisy)")
    ap.add_argument("--rows", nargs="+", type=int, default=None, metavar="I",
                    help="--stress: these recording indices (instead of --first/--n)")
    args = ap.parse_args(argv)
    if args.stress:
        import diagnose_stress  # bench/diagnose_stress.py
        return diagnose_stress.main(args)
    if args.rig:
        return rig_table(args)
    n = 1 if args.quick else args.seeds
    rng = np.random.default_rng(2026)
    effects = args.effects or (list(EFFECTS) + ["clean"])
    # warm up the compiled kernels so the first row's time is not compile time
    run, _, _, base = concealed_run(None, duration=0.5, seed=99)
    diagnose(run, base, candidates=["coulomb_friction", "higher_mode"])
    print(f"{'effect':21s} {'n':>2s} {'first':>6s} {'any':>5s} {'wrong first':>20s} "
          f"{'NRMSE base':>10s} {'refit':>8s} {'after':>8s} {'t [s]':>6s}")
    total = collections.Counter()
    for eff in effects:
        t = Tally(eff)
        for k in range(n):
            s = 1.0 if args.quick else float(rng.uniform(*args.strength))
            run, _, _, base = concealed_run(None if eff == "clean" else eff, s, seed=1000 + k, snr_db=args.snr)
            t.diagnose(run, base)
        print(f"{t.row()} {np.median(t.nb):10.4f} {np.median(t.nr):8.4f} {np.median(t.na):8.4f} "
              f"{np.median(t.ts):6.1f}", flush=True)
        total["runs"] += n
        total["time"] += sum(t.ts)
    print(f"{total['runs']} diagnoses, {total['time'] / max(total['runs'], 1):.1f} s each on average "
          "('any' on the clean row is the false-alarm rate)")
    return 0


class Tally:
    """Diagnoses of recordings with one effect concealed: how often it is named first / anything
    is named, the most common wrong first id, held-out NRMSE (baseline, null refit, after), time."""

    def __init__(self, effect: str):
        self.effect = effect
        self.firsts = self.anys = 0
        self.wrong = collections.Counter()
        self.nb, self.nr, self.na, self.ts = [], [], [], []

    def diagnose(self, run, baseline):
        t0 = time.perf_counter()
        d = diagnose(run, baseline)
        self.ts.append(time.perf_counter() - t0)
        ids = [m["id"] for m in d.missing]
        self.anys += bool(ids)
        if ids and ids[0] == self.effect:
            self.firsts += 1
        elif ids:
            self.wrong[ids[0]] += 1
        self.nb.append(d.fit_before["nrmse"]["validation"])
        self.nr.append(d.null.nrmse["validation"])
        self.na.append(d.best_fit.nrmse["validation"])

    def row(self) -> str:
        """effect, n, first, any, wrong first (the leading columns of both tables)."""
        n = len(self.ts)
        w = ", ".join(f"{i}x{c}" for i, c in self.wrong.most_common(1)) or "-"
        first = "-" if self.effect == "clean" else f"{self.firsts / n:.2f}"
        return f"{self.effect:21s} {n:2d} {first:>6s} {self.anys / n:5.2f} {w:>20s}"


# the simulated rig's effects (sim_backend [effects] keys) at their "concealed" level, scaled by the strength
RIG_EFFECTS = {
    "coulomb_friction": lambda s: {"coulomb_friction": 0.03 * s},
    "quadratic_damping": lambda s: {"quadratic_damping": 10.0 * s},
    "contact_stiffness": lambda s: {"contact_gap": 1.0e-3, "contact_stiffness": 1500.0 * s},
    "sensor_scale": lambda s: {"tip_scale_error": 0.02 * s},
    "parameter_drift": lambda s: {"stiffness_drift": 5e-4 * s},
    "higher_mode": lambda s: {"higher_mode_frequency": 60.0, "higher_mode_participation": 0.5 * s},
    "clean": lambda s: {},
}


def rig_table(args) -> int:
    import importlib.util
    from pathlib import Path

    spec = importlib.util.spec_from_file_location(
        "rig_helper", Path(__file__).resolve().parent.parent / "tests" / "test_diagnosis_rig.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    rng = np.random.default_rng(7)
    n = 1 if args.quick else args.seeds
    print(f"{'rig effect':21s} {'n':>2s} {'first':>6s} {'any':>5s} {'wrong first':>20s} "
          f"{'NRMSE base':>10s} {'after':>8s} {'t [s]':>6s}")
    for eff in (args.effects or list(RIG_EFFECTS)):
        t = Tally(eff)
        for k in range(n):
            s = 1.0 if args.quick else float(rng.uniform(*args.strength))
            run, model = mod.rig_run(RIG_EFFECTS[eff](s), seed=100 + k)
            t.diagnose(run, model)
        print(f"{t.row()} {np.median(t.nb):10.4f} {np.median(t.na):8.4f} {np.median(t.ts):6.1f}", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

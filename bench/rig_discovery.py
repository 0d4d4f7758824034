"""The closed loop on the simulated rig: each simulator effect concealed in turn, discovered by
`shakerlab acquire --diagnose --auto` (docs/closed-loop.md).

For every effect (one at a time, its size drawn from --seed inside a range where it matters on the
protocol; and the clean specimen) the command runs in a subprocess on the in-process simulated rig
with the effect in a --sim-config, and the table gives: the effect and its setting, the id the loop
named, the fitted size against the setting, the held-out NRMSE before/after, the rounds and stages
added, the loop's stop and the wall time.

    python bench/rig_discovery.py                       # every effect, the short protocol, 1 kHz
    python bench/rig_discovery.py --effects clean,offset --seed 3 --jsonl out.jsonl

The default protocol is a short one (a few seconds per stage) sampled at 1 kHz, so each diagnosis
takes about a minute on two cores; --protocol and --rate change them.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from rig.config import DEFAULT_RIG_PATH  # noqa: E402
from sim_backend.config import default_config  # noqa: E402

SHORT_PROTOCOL = """
[run]
settle_s = 0.5
[linear]
frequency_hz = 8.0
amplitude_vpp = 0.4
duration_s = 2.0
[resonance_search]
start_hz = 8.0
stop_hz = 24.0
steps = 6
refine_steps = 2
amplitude_vpp = 0.05
settle_s = 0.5
measure_s = 0.5
[nonlinear]
frequency_factor = 0.88
start_vpp = 0.5
step_factor = 2.0
max_vpp = 4.0
dwell_s = 1.0
analysis_s = 0.5
hold_s = 2.0
thd_threshold = 0.012
[[validation]]
frequency_factor = 0.7
amplitude_fraction = 1.0
duration_s = 2.0
"""

# the same with its nonlinear stage at one level (--single-level)
SINGLE_LEVEL_PROTOCOL = SHORT_PROTOCOL.replace("start_vpp = 0.5", "start_vpp = 4.0")
assert SINGLE_LEVEL_PROTOCOL != SHORT_PROTOCOL and "max_vpp = 4.0" in SHORT_PROTOCOL
# --validation-factor rewrites the one validation stage's factor (the nonlinear stage's is 0.88)
assert SHORT_PROTOCOL.count("frequency_factor = 0.7\n") == 1

# effect: (catalog id, the id's size parameter, the simulator settings for a size s, size range,
#          the expected fitted value for a size s)
EFFECTS = {
    "coulomb_friction": ("coulomb_friction", "mu", lambda s: {"effects": {"coulomb_friction": s}}, (0.05, 0.3),
                         lambda s: s),
    "quadratic_damping": ("quadratic_damping", "c2", lambda s: {"effects": {"quadratic_damping": s}}, (5.0, 30.0),
                          lambda s: s),
    "contact_stiffness": ("contact_stiffness", "kc",
                          lambda s: {"effects": {"contact_stiffness": s, "contact_gap": 0.8e-3}}, (2e3, 2e4),
                          lambda s: s),
    "channel_delay": ("channel_delay", "delay", lambda s: {"effects": {"channel_delay": s}}, (0.5e-3, 2e-3),
                      lambda s: s),
    "tip_scale_error": ("sensor_scale", "tip_scale", lambda s: {"effects": {"tip_scale_error": s}}, (0.005, 0.03),
                        lambda s: s),
    "base_scale_error": ("sensor_scale", "tip_scale", lambda s: {"effects": {"base_scale_error": s}},
                         (0.005, 0.03), lambda s: -s),
    "stiffness_drift": ("parameter_drift", "drift", lambda s: {"effects": {"stiffness_drift": s}}, (0.002, 0.01),
                        lambda s: s),
    "higher_mode": ("higher_mode", "phi2",
                    lambda s: {"effects": {"higher_mode_frequency": 60.0, "higher_mode_participation": s}},
                    (0.05, 0.2), lambda s: s),
    "offset": ("offset", "y^0", lambda s: {"effects": {"offset": s}}, (0.5, 3.0), lambda s: s),
    # the specimen's own term is taken out, so the effect is the only one of its kind
    "cubic_stiffness": ("cubic_stiffness", "y^3",
                        lambda s: {"specimen": {"fn_m": {"y^3": 0.0}}, "effects": {"cubic_stiffness": s}},
                        (5e7, 3e8), lambda s: s),
    "amplitude_damping": ("amplitude_damping", "y^2*dy",
                          lambda s: {"specimen": {"fn_m": {"y^2*dy": 0.0}}, "effects": {"amplitude_damping": s}},
                          (5e4, 4e5), lambda s: s),
}


# effects of a kind the reconstructed model itself holds (its library has the term): found when the
# reconstruction carries the term at the effect's size, not by the diagnosis naming it
IN_MODEL_CLASS = ("cubic_stiffness", "amplitude_damping")


def toml_of(d: dict, prefix: str = "") -> str:
    """A nested dict of numbers as TOML tables."""
    lines, tables = [], []
    for k, v in d.items():
        if isinstance(v, dict):
            tables.append((k, v))
        else:
            key = k if k.replace("_", "").isalnum() else json.dumps(k)
            lines.append(f"{key} = {float(v)!r}")
    out = (f"[{prefix}]\n" if prefix and lines else "") + "\n".join(lines) + ("\n" if lines else "")
    for k, v in tables:
        key = k if k.replace("_", "").isalnum() else json.dumps(k)
        out += toml_of(v, f"{prefix}.{key}" if prefix else key)
    return out


def merge(a: dict, b: dict) -> dict:
    out = dict(a)
    for k, v in b.items():
        out[k] = merge(out.get(k, {}), v) if isinstance(v, dict) else v
    return out


def fitted(named: dict, key: str):
    for k, v in named.get("parameters", {}).items():
        if k.split(":")[-1] == key:
            return v.get("value")
    return None


def run_case(effect: str, size: float | None, workdir: Path, protocol: Path, rig: Path, seed: int,
             max_rounds: int, noise_std: float | None = None) -> dict:
    sim = {} if effect == "clean" else EFFECTS[effect][2](size)
    if noise_std is not None:                   # a noisier (or quieter) laser than the simulator's default
        sim = merge(sim, {"sensors": {"noise_std": noise_std}})
    if effect == "cubic_stiffness" or effect == "amplitude_damping":      # keep the specimen's other terms
        sim = merge({"specimen": {"fn_m": dict(default_config()["specimen"]["fn_m"])}}, sim)
    sim_path = workdir / f"{effect}.sim.toml"
    sim_path.write_text(toml_of(sim))
    out = workdir / f"{effect}.h5"
    cmd = [sys.executable, "-m", "shakerlab.cli", "acquire", "--config", str(rig), "--simulated", "--protocol",
           str(protocol), "-o", str(out), "--sim-speed", "0", "--quiet", "--seed", str(seed), "--sim-config",
           str(sim_path), "--diagnose", "--auto", "--json", "--max-rounds", str(max_rounds)]
    t0 = time.monotonic()
    p = subprocess.run(cmd, capture_output=True, text=True, env={**os.environ, "PYTHONPATH": str(ROOT)})
    wall = time.monotonic() - t0
    row = {"effect": effect, "setting": size, "wall_s": wall, "exit": p.returncode,
           **({"noise_std": noise_std} if noise_std is not None else {})}
    (workdir / f"{effect}.json").write_text(p.stdout)
    try:
        doc = json.loads(p.stdout)
    except json.JSONDecodeError:
        row["error"] = (p.stderr.strip().splitlines() or ["no output"])[-1]
        return row
    d = doc["diagnosis"]
    if d is None:       # the protocol itself did not complete (a trip, an error): not diagnosed
        row["error"] = doc["stop_reason"]
        return row
    named = d.get("missing_physics", [])
    row.update(named=[m["id"] for m in named], stop=doc["stop"], rounds=len(doc["rounds"]),
               stages_added=[s for r in doc["rounds"] for s in r["stages_added"]],
               purposes=[r.get("purpose") for r in doc["rounds"]],
               first_round=(doc["rounds"][0]["before"]["result"] if doc["rounds"] else d["result"]),
               first_decision=(doc["rounds"][0].get("why") if doc["rounds"] else None),
               held_out_before=(d.get("fit_before") or {}).get("held_out_nrmse"),
               held_out_after=(d.get("fit_after") or {}).get("held_out_nrmse"))
    if effect != "clean":
        cid, key, _, _, expect = EFFECTS[effect]
        match = next((m for m in named if m["id"] == cid), None)
        row["expected_id"] = cid
        row["fitted"] = fitted(match, key) if match else None
        row["expected"] = expect(size)
        row["named_first"] = bool(named) and named[0]["id"] == cid
        if match is None and not named and effect in IN_MODEL_CLASS:
            # a term the reconstruction's own library holds is found as a term of the model, not named
            # as missing: its size is the reconstructed coefficient (the specimen's own is 0 here)
            fn = ((d.get("augmented_model") or {}).get("baseline") or {}).get("parameters", {}).get("fn_m", {})
            if key in fn:
                row["fitted"], row["found_in"] = fn[key], f"the model's {key}"
                row["named_first"] = True
        row["error_pct"] = (100 * (row["fitted"] / row["expected"] - 1) if row["fitted"] is not None else None)
    else:
        row["named_first"] = not named
    return row


def fmt(v, spec=".3g"):
    return "-" if v is None else format(v, spec)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--effects", default="clean," + ",".join(EFFECTS),
                    help="comma-separated: clean and/or " + ", ".join(EFFECTS))
    ap.add_argument("--seed", type=int, default=0, help="draws the sizes (and the rig's noise)")
    ap.add_argument("--protocol", type=Path, help="protocol TOML (default: a short one)")
    ap.add_argument("--single-level", action="store_true",
                    help="the short protocol with its nonlinear stage at one level (4 Vpp): fewer amplitudes to "
                         "tell amplitude-dependent effects apart")
    ap.add_argument("--validation-factor", type=float, default=0.7,
                    help="the short protocol's validation frequency, times the resonance found (default 0.7). "
                         "At 0.78 the validation stage reaches about 40 %% of the nonlinear stage's peak, so it "
                         "alone is held out")
    ap.add_argument("--rate", type=float, default=1000.0, help="acquisition sample rate, Hz (default 1000)")
    ap.add_argument("--max-rounds", type=int, default=2)
    ap.add_argument("--sizes", default="", metavar="EFFECT=SIZE,...",
                    help="sizes instead of the drawn ones (e.g. near a detection limit: coulomb_friction=0.008)")
    ap.add_argument("--jsonl", type=Path, help="append one JSON row per case")
    ap.add_argument("--keep", type=Path, metavar="DIR",
                    help="keep each case's run file and the loop's JSON output in DIR, a new or empty folder "
                         "(default: a temporary directory, removed)")
    ap.add_argument("--noise-std", type=float, help="the lasers' white noise, m per sample (the simulator's "
                                                    "default: 2e-7)")
    args = ap.parse_args(argv)
    if (args.single_level or args.validation_factor != 0.7) and args.protocol is not None:
        ap.error("--single-level and --validation-factor change the short protocol; they do not apply to --protocol")
    if args.keep is not None and args.keep.exists() and (not args.keep.is_dir() or any(args.keep.iterdir())):
        ap.error(f"--keep {args.keep}: give a new or empty folder (its run files and JSON would be written over)")
    if not 0.2 <= args.validation_factor <= 2.0:
        ap.error(f"--validation-factor {args.validation_factor} is outside 0.2-2 (times the resonance)")
    rng = np.random.default_rng(args.seed)
    sizes = {e: float(np.exp(rng.uniform(np.log(lo), np.log(hi)))) for e, (_, _, _, (lo, hi), _) in EFFECTS.items()}
    for item in filter(None, args.sizes.split(",")):
        name, value = item.split("=")
        sizes[name.strip()] = float(value)
    effects = [e.strip() for e in args.effects.split(",") if e.strip()]
    unknown = [e for e in effects if e != "clean" and e not in EFFECTS]
    if unknown:
        ap.error(f"unknown effect(s) {unknown}")
    rows = []
    t_all = time.monotonic()
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp) if args.keep is None else args.keep
        work.mkdir(parents=True, exist_ok=True)
        protocol = args.protocol or work / "protocol.toml"
        if args.protocol is None:
            text = SINGLE_LEVEL_PROTOCOL if args.single_level else SHORT_PROTOCOL
            protocol.write_text(text.replace("frequency_factor = 0.7\n",
                                             f"frequency_factor = {args.validation_factor!r}\n"))
        rig = work / "rig.toml"
        rig.write_text(DEFAULT_RIG_PATH.read_text().replace("sample_rate_hz = 10000.0",
                                                              f"sample_rate_hz = {args.rate!r}"))
        print(f"{'effect':18s} {'setting':>9s} {'named':28s} {'fitted':>9s} {'err %':>7s} {'NRMSE before':>12s} "
              f"{'after':>9s} {'rounds':>6s} {'stop':10s} {'wall s':>7s}  stages added", flush=True)
        for e in effects:
            row = run_case(e, None if e == "clean" else sizes[e], work, protocol, rig, args.seed, args.max_rounds,
                           args.noise_std)
            rows.append(row)
            if args.jsonl:
                with open(args.jsonl, "a") as fh:
                    fh.write(json.dumps(row) + "\n")
            if "error" in row:
                print(f"{e:18s} {fmt(row['setting']):>9s} ERROR: {row['error']}", flush=True)
                continue
            said = ",".join(row["named"]) or (f"(in {row['found_in']})" if row.get("found_in") else "(nothing)")
            print(f"{e:18s} {fmt(row['setting']):>9s} {said:28s} "
                  f"{fmt(row.get('fitted')):>9s} {fmt(row.get('error_pct'), '+.1f'):>7s} "
                  f"{fmt(row['held_out_before'], '.4g'):>12s} {fmt(row['held_out_after'], '.4g'):>9s} "
                  f"{row['rounds']:>6d} {row['stop']:10s} {row['wall_s']:7.0f}  {','.join(row['stages_added']) or '-'}",
                  flush=True)
    ok = [r for r in rows if r.get("named_first")]
    within = [r for r in rows if r.get("error_pct") is not None and abs(r["error_pct"]) <= 10]
    print(f"\n{len(ok)}/{len(rows)} named first (clean: nothing named; a term the model holds: found in it); {len(within)} within 10 % of the setting; "
          f"{sum(1 for r in rows if r.get('rounds'))} needed an added round; total wall time "
          f"{time.monotonic() - t_all:.0f} s")
    # the cases the loop exists for: a first round that could not decide (ambiguous, or an effect
    # undecided), and whether the stage it added named the concealed effect; and the named effects
    # whose size the first record did not determine (a sizing round)
    open_first = [r for r in rows if r.get("rounds") and r.get("effect") != "clean"
                  and (r.get("purposes") or ["separate"])[0] != "size"]
    settled = [r for r in open_first if r.get("named_first")]
    for r in open_first:
        print(f"  {r['effect']} {fmt(r['setting'])}: first round undecided or ambiguous "
              f"({(r.get('first_decision') or '')[:90]}...); after {r['rounds']} round(s): "
              f"{','.join(r['named']) or 'nothing named'}", flush=True)
    print(f"{len(open_first)} first round(s) that could not decide; the added stage named the concealed "
          f"effect on {len(settled)}")
    sized = [r for r in rows if "size" in (r.get("purposes") or [])]
    print(f"{len(sized)} case(s) with a sizing round (a named effect's size not determined by the record "
          f"before it): " + ", ".join(f"{r['effect']} {fmt(r.get('error_pct'), '+.1f')} %" for r in sized))
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""`python bench/diagnose.py --stress`: the diagnosis on recordings of the independent generator
(issue 13). The recordings, the rows and the report are recon.testing.stress and
recon.testing.diagnosis_stress (one copy, shared with the tests); this module runs them over
processes, saves rows (--jsonl) and reads saved rows back (--from-jsonl, --rescore, --oracle-of).
"""
from __future__ import annotations

import json
import multiprocessing as mp
import os
import time

from recon.testing.diagnosis_stress import RUN_ONE, block_of, oracle_of_stored, report_apart, rescore


def load_rows(paths: list[str]) -> list[dict]:
    """Rows saved by --jsonl, joined by block and recording index (a later file's row replaces an
    earlier one; the blocks' indices are their own: random #3 and pair #3 are two recordings)."""
    rows = {}
    for p in paths:
        try:
            with open(p) as f:
                for n, line in enumerate(f, 1):
                    if line.strip():
                        r = json.loads(line)
                        rows[(block_of(r), r["index"])] = r
        except OSError as exc:
            raise SystemExit(f"{p}: cannot read it ({exc.strerror})")
        except (json.JSONDecodeError, KeyError, TypeError) as exc:
            raise SystemExit(f"{p}, line {n}: not a row saved by --jsonl ({type(exc).__name__}: {exc})")
    return [rows[k] for k in sorted(rows, key=lambda k: (k[0] != "random", k))]


def block_flag(args) -> str:
    """The block the flags ask for (--corner, --pairs, --weak-linear: at most one), else "random"."""
    asked = [b for b, flag in (("corner", "corner"), ("pairs", "pairs"), ("weak_linear", "weak_linear"))
             if getattr(args, flag, False)]
    if len(asked) > 1:
        raise SystemExit("--corner, --pairs and --weak-linear are blocks of their own: name one")
    return asked[0] if asked else "random"


def main(args) -> int:
    if getattr(args, "oracle_of", None):
        rows = load_rows(args.oracle_of)
        if not args.jsonl:
            raise SystemExit("--oracle-of needs --jsonl OUT (the rows with their oracle)")
        try:
            out = open(args.jsonl, "x")
        except FileExistsError:
            raise SystemExit(f"--jsonl: {args.jsonl} exists; name a new file (saved rows are never overwritten)")
        if args.workers > 1:     # a process per core: the fits' finite differences on one thread each
            os.environ.setdefault("SHAKERLAB_THREADS", "1")
        pool = mp.get_context("fork").Pool(max(1, min(args.workers, 2))) if args.workers > 1 else None
        done = []
        with out:
            for r in (pool.imap(oracle_of_stored, rows) if pool else map(oracle_of_stored, rows)):
                done.append(r)
                out.write(json.dumps(r, default=float) + "\n")
                out.flush()
                o = r.get("oracle")
                print(f"#{r['index']} {r['effect']} {r['protocol']}: first={r.get('first')} oracle="
                      + ("-" if o is None else o.get("stale") or o.get("failed")
                         or f"{'significant' if o['significant'] else 'not significant'} "
                            f"({o['held_out_nrmse']:.5f} vs {o['reference_held_out_nrmse']:.5f})"), flush=True)
        if pool:
            pool.close()
        print("\n".join(report_apart(done)))
        return 0
    if getattr(args, "rescore", None):
        rows = load_rows(args.rescore)
        if not rows:
            raise SystemExit(f"--rescore: no rows in {', '.join(args.rescore)}")
        print("\n".join(rescore(rows)))
        return 0
    if getattr(args, "from_jsonl", None):
        rows = load_rows(args.from_jsonl)
        if not rows:
            raise SystemExit(f"--from-jsonl: no rows in {', '.join(args.from_jsonl)}")
        idx = [r["index"] for r in rows]
        print(f"{len(rows)} saved rows of the independent generator (#{min(idx)}..#{max(idx)}) from "
              f"{', '.join(args.from_jsonl)}")
        print("\n".join(report_apart(rows)))
        return 0
    ids = list(args.rows) if getattr(args, "rows", None) else list(range(args.first, args.first + args.n))
    n = len(ids)
    workers = max(1, min(args.workers, 2))
    out = None
    if args.jsonl:
        # rows are appended as they come (a stopped run keeps them); an existing file is never truncated
        try:
            out = open(args.jsonl, "x")
        except FileExistsError:
            raise SystemExit(f"--jsonl: {args.jsonl} exists; name a new file (saved rows are never overwritten)")
    rows = []
    t0 = time.perf_counter()
    if workers > 1:     # a process per core: the fits' finite differences on one thread each
        os.environ.setdefault("SHAKERLAB_THREADS", "1")
    pool = mp.get_context("fork").Pool(workers) if workers > 1 else None
    one = RUN_ONE[block_flag(args)]
    it = pool.imap_unordered(one, ids) if pool else map(one, ids)
    for k, r in enumerate(it, 1):
        rows.append(r)
        if out:
            out.write(json.dumps(r, default=float) + "\n")
            out.flush()
        effects = " + ".join(f"{e} ({x:.2f})" for e, x in [(r["effect"], r["strength"])] + list(r.get("also", [])))
        noise = (f"snr {r['snr']:g}" if r.get("snr") is not None else f"noise {r.get('noise_m', 0) * 1e6:.2g} um") \
            + (f" (linear stage {r['linear_snr']:g})" if r.get("linear_snr") is not None else "")
        print(f"[{k}/{n}] #{r['index']} {effects} {r['protocol']} fs {r['fs']:g} {noise}: {r['status']} "
              f"first={r.get('first')} named={r.get('named')} "
              + (f"both={r['both']} " if "both" in r else "")
              + (f"linear reported too noisy={r['linear_reported_noisy']} " if "linear_reported_noisy" in r else "")
              + f"sim {r.get('sim_seconds', 0):.1f} s diag {r.get('seconds', 0):.1f} s"
              + (f" {'REFUSED' if r['status'] == 'refused' else 'ERROR'} {r['error'][:160]}" if "error" in r else ""),
              flush=True)
    if pool:
        pool.close()
        pool.join()
    if out:
        out.close()
    print(f"\n{n} recordings of the independent generator ({block_flag(args)} block, #{min(ids)}..#{max(ids)}), "
          f"{workers} worker(s), "
          f"wall {time.perf_counter() - t0:.0f} s")
    print("\n".join(report_apart(rows)))
    return 0

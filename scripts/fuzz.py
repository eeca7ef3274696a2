#!/usr/bin/env python3
"""Fuzz the decoders and loaders (atheris harnesses in fuzz/) and report per harness the
executions, execs/s, crashes and peak RSS; writes JSON.

    python scripts/fuzz.py --runs 100000                      # every harness, 10^5 executions each
    python scripts/fuzz.py msg_est msg_meas --seconds 300     # some harnesses, 5 minutes each
    python scripts/fuzz.py --seeds                            # rewrite the committed seed corpus
    python scripts/fuzz.py msg_meas --runs 1000000 --keep-found   # and keep what reached new code
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from fuzz.runner import harnesses, keep_found, run_harness, write_seeds


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("harness", nargs="*", help=f"harnesses to run (default: all: {', '.join(harnesses())})")
    ap.add_argument("--runs", type=int, help="executions per harness")
    ap.add_argument("--seconds", type=float, help="time per harness")
    ap.add_argument("--timeout", type=int, default=10, help="seconds one input may take (a hang otherwise)")
    ap.add_argument("--rss-limit-mb", type=int, default=2048, help="memory one harness may use")
    ap.add_argument("--keep-going", action="store_true", help="start a harness again after a crash until its budget is spent")
    ap.add_argument("--out", type=Path, default=Path("runs/fuzz"), help="scratch corpus, artifacts, logs and the JSON")
    ap.add_argument("--seeds", action="store_true", help="rewrite the seed corpus in fuzz/corpus and stop")
    ap.add_argument("--keep-found", action="store_true",
                    help="after the run, add to fuzz/corpus the inputs that reached new code (libFuzzer's -merge)")
    a, extra = ap.parse_known_args()
    if a.seeds:
        for h, n in write_seeds().items():
            print(f"{h}: {n} seeds")
        return 0
    if a.runs is None and a.seconds is None:
        ap.error("give --runs or --seconds")
    names = a.harness or harnesses()
    a.out.mkdir(parents=True, exist_ok=True)
    out = a.out.resolve()
    rows = []
    print(f"{'harness':<16} {'executions':>11} {'s':>7} {'execs/s':>9} {'crashes':>7} {'peak RSS MB':>11} {'cov':>5}")
    for h in names:
        r = run_harness(h, out, a.runs, a.seconds, a.timeout, a.rss_limit_mb, a.keep_going, extra)
        rows.append(r.as_dict())
        print(f"{h:<16} {r.executions:>11} {r.seconds:>7} {r.execs_per_s:>9} {r.crashes:>7} {r.peak_rss_mb:>11} {r.coverage:>5}", flush=True)
        for art in r.artifacts:
            print(f"    {art}")
        (out / "fuzz.json").write_text(json.dumps(rows, indent=1) + "\n")
        if a.keep_found:
            print(f"    kept {len(keep_found(h, out))} inputs that reached new code in fuzz/corpus/{h}")
    print(f"wrote {out / 'fuzz.json'}")
    return 1 if any(r["crashes"] for r in rows) else 0


if __name__ == "__main__":
    sys.exit(main())

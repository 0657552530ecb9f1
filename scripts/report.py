#!/usr/bin/env python3
"""The reliability report of a test run (scripts/test.sh prints it at the end).

    scripts/report.py REPORT_DIR

Reads REPORT_DIR/reliability.jsonl (one line per scenario, written by the tests through
sim_drives::report::Scenario::record) and REPORT_DIR/fuzz.jsonl (one line per fuzz target,
written by scripts/fuzz.sh), prints the figures and writes them to REPORT_DIR/summary.json.
Exit status 1 when data was lost, something panicked (a fuzz crash counts as a panic), a stop
came later than its bound, or a line cannot be read; 0 otherwise.
"""
import json
import sys
from pathlib import Path


def lines(path):
    """(records, unreadable line count) of a JSON-lines file; a missing file is empty."""
    out, bad = [], 0
    if path.exists():
        for ln in path.read_text(encoding="utf-8", errors="replace").splitlines():
            if not ln.strip():
                continue
            try:
                out.append(json.loads(ln))
            except json.JSONDecodeError:
                bad += 1
    return out, bad


def main():
    if len(sys.argv) != 2:
        print(__doc__.strip(), file=sys.stderr)
        return 2
    d = Path(sys.argv[1])
    sc, bad1 = lines(d / "reliability.jsonl")
    fz, bad2 = lines(d / "fuzz.jsonl")
    n = lambda r, k: int(r.get(k) or 0)  # noqa: E731
    with_stop = [r for r in sc if r.get("stop_cycles") is not None and r.get("bound_cycles") is not None]
    late = [r["scenario"] for r in with_stop if not r.get("within_bound", True)]
    fuzz = {}
    for r in fz:
        t = fuzz.setdefault(r.get("target", "?"), {"executions": 0, "seconds": 0, "crashes": 0})
        for k in t:
            t[k] += n(r, k)
    summary = {
        "scenarios_run": len(sc),
        "faults_injected": sum(n(r, "faults_injected") for r in sc),
        "stops_within_bound": len(with_stop) - len(late),
        "stops_measured": len(with_stop),
        "data_lost": sum(n(r, "data_lost") for r in sc),
        "panics": sum(n(r, "panics") for r in sc) + sum(t["crashes"] for t in fuzz.values()),
        "fuzz_executions": {k: v["executions"] for k, v in sorted(fuzz.items())},
        "unreadable_lines": bad1 + bad2,
    }
    (d / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")

    print(f"reliability report ({d})")
    print(f"  scenarios run        {summary['scenarios_run']}")
    print(f"  faults injected      {summary['faults_injected']}")
    print(f"  stops within bound   {summary['stops_within_bound']} of {summary['stops_measured']}")
    print(f"  data lost            {summary['data_lost']}   (must be 0)")
    print(f"  panics               {summary['panics']}   (must be 0)")
    if fuzz:
        print("  fuzz executions per target")
        for k, v in sorted(fuzz.items()):
            print(f"    {k:<8} {v['executions']:>12,} in {v['seconds']} s, crashes {v['crashes']}")
    else:
        print("  fuzz executions per target: none (fuzzing did not run)")
    failed = []
    if summary["data_lost"]:
        failed.append(f"{summary['data_lost']} item(s) of data lost")
    if summary["panics"]:
        who = [r["scenario"] for r in sc if n(r, "panics")] + [k for k, v in fuzz.items() if v["crashes"]]
        failed.append(f"{summary['panics']} panic(s): {', '.join(who)}")
    if late:
        failed.append(f"stops later than their bound: {', '.join(late)}")
    if summary["unreadable_lines"]:
        failed.append(f"{summary['unreadable_lines']} unreadable report line(s)")
    for f in failed:
        print(f"FAILED: {f}")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())

"""Where the suite's time goes, from the files ``LLRMPP_SUITE_PROFILE=DIR make test`` leaves
(``tests/helpers/suite_profile.py``): per worker and in all, the tests' wall seconds split
into JAX tracing, lowering, compiling (or loading from the persistent cache) and the rest
(running, Python, the CLI tests' subprocesses), and the modules that cost most.

Usage::

    LLRMPP_SUITE_PROFILE=~/runs/profile-cold make test
    python experiments/suite_profile.py ~/runs/profile-cold [--label cold] [--out FILE.json]
"""

from __future__ import annotations

import argparse
import glob
import json
import os
from collections import defaultdict

FIELDS = ("wall_s", "trace_s", "lower_s", "compile_s", "programs", "hits")


def load(folder: str) -> dict[str, dict[str, float]]:
    """Every worker's per-test records, merged (test id -> record)."""
    tests: dict[str, dict[str, float]] = {}
    files = sorted(glob.glob(os.path.join(folder, "*.json")))
    if not files:
        raise SystemExit(
            f"suite_profile: no profile files in {folder} (run the suite with LLRMPP_SUITE_PROFILE={folder})"
        )
    for path in files:
        with open(path) as f:
            tests.update(json.load(f))
    return tests


def summarise(tests: dict[str, dict[str, float]], top: int = 15) -> dict:
    """Totals, the rest (wall minus the three JAX phases) and the dearest modules."""
    total = {k: sum(t.get(k, 0.0) for t in tests.values()) for k in FIELDS}
    total["rest_s"] = total["wall_s"] - total["trace_s"] - total["lower_s"] - total["compile_s"]
    modules: dict[str, dict[str, float]] = defaultdict(lambda: dict.fromkeys(FIELDS, 0.0))
    for nodeid, t in tests.items():
        m = modules[nodeid.split("::")[0]]
        for k in FIELDS:
            m[k] += t.get(k, 0.0)
    for m in modules.values():
        m["rest_s"] = m["wall_s"] - m["trace_s"] - m["lower_s"] - m["compile_s"]
    dearest = sorted(modules.items(), key=lambda kv: -kv[1]["wall_s"])[:top]
    return {
        "tests": len(tests),
        "total": {k: round(v, 1) for k, v in total.items()},
        "modules": {name: {k: round(v, 1) for k, v in m.items()} for name, m in dearest},
    }


def main() -> None:
    p = argparse.ArgumentParser(
        description=(__doc__ or "").split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument("folder", help="the LLRMPP_SUITE_PROFILE folder a suite run wrote")
    p.add_argument("--label", default="", help="a name for this run in the JSON (e.g. cold, warm)")
    p.add_argument("--top", type=int, default=15, help="how many of the dearest modules to list (default 15)")
    p.add_argument("--out", help="write the summary as JSON here (default: print only)")
    args = p.parse_args()
    summary = {"label": args.label, **summarise(load(os.path.expanduser(args.folder)), args.top)}
    t = summary["total"]
    print(
        f"{summary['tests']} tests, {t['wall_s']:.0f} test-seconds (both workers): trace {t['trace_s']:.0f}, "
        f"lower {t['lower_s']:.0f}, compile/load {t['compile_s']:.0f} ({t['programs']:.0f} programs, "
        f"{t['hits']:.0f} from the cache), rest {t['rest_s']:.0f}"
    )
    for name, m in summary["modules"].items():
        print(
            f"  {m['wall_s']:7.1f} s  {name}: trace {m['trace_s']:.1f}, lower {m['lower_s']:.1f}, "
            f"compile {m['compile_s']:.1f}, rest {m['rest_s']:.1f}"
        )
    if args.out:
        with open(args.out, "w") as f:
            json.dump(summary, f, indent=1)
            f.write("\n")


if __name__ == "__main__":
    main()

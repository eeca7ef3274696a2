"""Write tests/durations.json, the seconds each test group took, from a pytest junit file.

`make test` writes runs/junit.xml; tests/conftest.py hands the groups to the two xdist
workers longest first from these numbers (the "docker" group, every test marked docker, and
one group per file for the rest). Refresh it after a CI run whose times changed:

    python scripts/test_durations.py runs/junit.xml
"""

from __future__ import annotations

import json
import subprocess
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def main(argv: list[str]) -> int:
    if len(argv) != 1:
        print(__doc__, file=sys.stderr)
        return 2
    tree = ET.parse(argv[0])
    # The docker group: the tests marked docker (tests/conftest.py puts them in one group),
    # as pytest collects them now.
    co = subprocess.run([sys.executable, "-m", "pytest", "--collect-only", "-q", "-m", "docker", "-p", "no:cacheprovider"],
                        cwd=ROOT, capture_output=True, text=True, timeout=600)
    docker = {line.strip() for line in co.stdout.splitlines() if "::" in line}
    if not docker:
        print(f"no test marked docker was collected:\n{co.stdout[-2000:]}{co.stderr[-2000:]}", file=sys.stderr)
        return 1
    seconds: dict[str, float] = {}
    for case in tree.iter("testcase"):
        path = case.get("classname", "").replace(".", "/") + ".py"
        group = "docker" if f"{path}::{case.get('name')}" in docker else Path(path).name
        seconds[group] = seconds.get(group, 0.0) + float(case.get("time", 0.0))
    out = ROOT / "tests" / "durations.json"
    out.write_text(json.dumps({g: round(s, 1) for g, s in sorted(seconds.items(), key=lambda kv: -kv[1])}, indent=1) + "\n")
    print(f"{out}: {len(seconds)} groups, {sum(seconds.values()):.0f} s in all")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))

"""Print the image's Python requirements, one per line, read from pyproject.toml.

The image holds the project's run-time dependencies plus the "vision" extra
(OpenCV, Open3D and pyrender's real dependencies); not the "test" extra.
pyrender itself is installed separately with --no-deps (it pins an old
PyOpenGL; see scripts/setup.sh), so it is not listed here.

Usage: python3 docker/requirements.py [pyproject.toml] > requirements.txt
"""
import re
import sys
import tomllib

EXTRAS = ("vision",)
# Imported by pyrender but not listed in pyproject.toml (pyrender is installed
# with --no-deps); drop once the "vision" extra names it.
MISSING = ("six>=1.16",)

with open(sys.argv[1] if len(sys.argv) > 1 else "pyproject.toml", "rb") as f:
    project = tomllib.load(f)["project"]
reqs = list(project["dependencies"])
for extra in EXTRAS:
    reqs += project.get("optional-dependencies", {}).get(extra, [])


def name(req: str) -> str:
    return re.split(r"[\s<>=!~;\[(]", req, maxsplit=1)[0].lower().replace("_", "-")


names = {name(r) for r in reqs}
reqs += [r for r in MISSING if name(r) not in names]
seen = set()
for r in reqs:
    if r not in seen:
        seen.add(r)
        print(r)

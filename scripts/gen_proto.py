#!/usr/bin/env python3
"""Generate the Python code of the bus messages from proto/swarm/v1/*.proto into swarmrt/bus/v1/.

The .proto files are the single source of truth; the generated ``swarmrt/bus/v1/*_pb2.py`` (and their type stubs
``*_pb2.pyi``, which the type checker reads) are committed (so a checkout runs without a code generator) and
``tests/test_proto_schema.py`` regenerates them and checks they are unchanged. The
compiler is the one bundled with ``grpcio-tools`` (pinned in constraints.txt): its
generated code matches the pinned protobuf runtime, which Debian's older protoc does
not promise.

The schema's package is ``swarm.v1`` (its files are ``swarm/v1/*.proto``, the names every language and
every recording use), but the generated classes belong to the runtime, not to the application package
``swarm``: protoc writes them as ``swarm/v1/`` in a scratch directory, and this script moves them to
``swarmrt/bus/v1/`` with their imports of each other (``from swarm.v1 import x_pb2``) rewritten to
``from swarmrt.bus.v1 import x_pb2``. Nothing else changes: the descriptors keep their file names and
full names (``swarm.v1.Estimate``), so payloads and recordings are the same bytes.

    python scripts/gen_proto.py            # rewrite swarmrt/bus/v1/*_pb2.py and *_pb2.pyi
    python scripts/gen_proto.py --out DIR  # write into DIR/swarmrt/bus/v1/ instead
"""

from __future__ import annotations

import argparse
import re
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
PROTO = ROOT / "proto"
#: Where the generated modules go, relative to the output root, and the package they import each other as.
PACKAGE_DIR = Path("swarmrt", "bus", "v1")
PACKAGE = "swarmrt.bus.v1"
_IMPORT = re.compile(r"^from swarm\.v1 import ", re.MULTILINE)


def proto_files() -> list[str]:
    """The schema files, relative to proto/ (their import paths), sorted."""
    return sorted(str(p.relative_to(PROTO)) for p in (PROTO / "swarm" / "v1").glob("*.proto"))


def generate(out: Path) -> list[Path]:
    from grpc_tools import protoc

    files = proto_files()
    dest = out / PACKAGE_DIR
    dest.mkdir(parents=True, exist_ok=True)
    written = []
    with tempfile.TemporaryDirectory() as scratch:
        code = protoc.main(["grpc_tools.protoc", f"-I{PROTO}", f"--python_out={scratch}", f"--pyi_out={scratch}", *files])
        if code != 0:
            raise SystemExit(f"protoc failed ({code})")
        for f in files:
            for suffix in ("_pb2.py", "_pb2.pyi"):
                made = Path(scratch) / f.replace(".proto", suffix)
                text = _IMPORT.sub(f"from {PACKAGE} import ", made.read_text())
                if "swarm.v1 import" in text.replace(f"{PACKAGE} import", ""):
                    raise SystemExit(f"{made.name}: an import of swarm.v1 this script does not know how to rewrite")
                target = dest / made.name
                target.write_text(text)
                written.append(target)
    return written


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", type=Path, default=ROOT, help="root to write swarmrt/bus/v1/*_pb2.py under (default: the repository)")
    a = p.parse_args(argv)
    for f in generate(a.out):
        print(f)
    return 0


if __name__ == "__main__":
    sys.exit(main())

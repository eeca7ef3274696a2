#!/usr/bin/env python3
"""Generate the Python code of the bus messages from proto/swarm/v1/*.proto.

The .proto files are the single source of truth; the generated ``swarm/v1/*_pb2.py`` (and their type stubs
``*_pb2.pyi``, which the type checker reads) are committed (so a checkout runs without a code generator) and
``tests/test_proto_schema.py`` regenerates them and checks they are unchanged. The
compiler is the one bundled with ``grpcio-tools`` (pinned in constraints.txt): its
generated code matches the pinned protobuf runtime, which Debian's older protoc does
not promise.

    python scripts/gen_proto.py            # rewrite swarm/v1/*_pb2.py and *_pb2.pyi
    python scripts/gen_proto.py --out DIR  # write into DIR/swarm/v1/ instead
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
PROTO = ROOT / "proto"


def proto_files() -> list[str]:
    """The schema files, relative to proto/ (their import paths), sorted."""
    return sorted(str(p.relative_to(PROTO)) for p in (PROTO / "swarm" / "v1").glob("*.proto"))


def generate(out: Path) -> list[Path]:
    from grpc_tools import protoc

    (out / "swarm" / "v1").mkdir(parents=True, exist_ok=True)
    files = proto_files()
    code = protoc.main(["grpc_tools.protoc", f"-I{PROTO}", f"--python_out={out}", f"--pyi_out={out}", *files])
    if code != 0:
        raise SystemExit(f"protoc failed ({code})")
    return [out / f.replace(".proto", suffix) for f in files for suffix in ("_pb2.py", "_pb2.pyi")]


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", type=Path, default=ROOT, help="root to write swarm/v1/*_pb2.py under (default: the repository)")
    a = p.parse_args(argv)
    for f in generate(a.out):
        print(f)
    return 0


if __name__ == "__main__":
    sys.exit(main())

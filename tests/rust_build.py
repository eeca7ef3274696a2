"""Building the Rust participants (``participants/<crate>``) for the tests that run them.

Every crate builds into one cargo target directory, ``participants/target`` (ignored by
git, kept between runs): the crates pin the same ``zenoh`` (=1.10.2, the same features)
and the same profiles, so they share its compiled dependency tree — a cold build of it
takes minutes on two cores; the second crate then compiles only itself, and a warm
rebuild of either takes seconds.
"""

from __future__ import annotations

import shutil
import subprocess
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
TARGET = ROOT / "participants" / "target"


def cargo() -> str:
    exe = shutil.which("cargo") or str(Path.home() / ".cargo" / "bin" / "cargo")
    assert Path(exe).exists(), "cargo not found: install the Rust toolchain (rustup) to build the Rust participants"
    assert shutil.which("protoc"), "protoc not found: install Debian's protobuf-compiler (scripts/apt-packages-dev.txt)"
    return exe


def build(crate: str, binary: str) -> Path:
    """``cargo build --locked`` of ``participants/<crate>`` (dev profile) into the shared
    target directory; returns the path of its executable ``binary``."""
    t0 = time.monotonic()
    p = subprocess.run([cargo(), "build", "--locked", "--target-dir", str(TARGET)], cwd=ROOT / "participants" / crate,
                       capture_output=True, text=True, timeout=3600)
    assert p.returncode == 0, p.stderr[-4000:]
    print(f"cargo build of {crate}: {time.monotonic() - t0:.0f} s")
    exe = TARGET / "debug" / binary
    assert exe.is_file(), exe
    return exe

"""Is every node of a cluster able to run this swarm, with the same numbers?

Before a cluster run the driver asks every Ray node (a small task pinned to it, sent by
value: it runs even where the project is not installed) for its Python, Ray, numpy and
project versions and a fingerprint of the project's code, and refuses to start, in one line
naming the node and what differs, when a node lacks the project (no venv, not the image) or
any of them differs from the driver's: a node with other code or another numpy would give
other numbers, and another Ray or Python may not even talk to the rest.
"""

from __future__ import annotations

import hashlib
from collections.abc import Callable
from pathlib import Path
from typing import Any

__all__ = ["code_fingerprint", "project_version", "make_probe", "mismatch", "ClusterError"]

#: The packages whose code makes the numbers (the roles, runtime and core) and the runs.
_PACKAGES = ("swarmcore", "swarmvision", "swarmrt", "world_sim", "sat_agent", "selector", "swarm")


class ClusterError(RuntimeError):
    """The cluster cannot run this swarm (one line saying why)."""


def project_version() -> str | None:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("swarm-coloc")
    except PackageNotFoundError:
        return None


def code_fingerprint() -> str:
    """sha256 (first 16 hex) over the project's Python sources, by relative path."""
    import importlib.util

    h = hashlib.sha256()
    for pkg in _PACKAGES:
        spec = importlib.util.find_spec(pkg)
        if spec is None or not spec.submodule_search_locations:
            h.update(f"{pkg}: missing\n".encode())
            continue
        root = Path(next(iter(spec.submodule_search_locations)))
        for p in sorted(root.rglob("*.py")):
            h.update(str(p.relative_to(root.parent)).encode())
            h.update(b"\0")
            h.update(p.read_bytes())
    return h.hexdigest()[:16]


def make_probe() -> Callable[[], dict[str, Any]]:
    """A function reporting what a node runs, built here so that it is pickled by value
    (cloudpickle sends a function defined in a function whole): it imports the project
    only inside a ``try``, so a node without it says so instead of failing to unpickle."""

    def probe() -> dict[str, Any]:
        import os
        import platform
        import socket

        facts: dict[str, Any] = {"python": platform.python_version(), "hostname": socket.gethostname(),
                                 "cpus": os.cpu_count(), "executable": __import__("sys").executable}
        try:
            import ray

            facts["ray"] = ray.__version__
            facts["ip"] = ray.util.get_node_ip_address()
        except Exception as exc:  # reported, not raised
            facts["ray"] = f"error: {exc}"
        try:
            from swarm.cluster.host import node_facts

            facts.update(node_facts())
        except Exception as exc:  # a node without the project says so
            facts["project"] = None
            facts["project_error"] = f"{type(exc).__name__}: {exc}"
        return facts

    return probe


def mismatch(node: str, theirs: dict[str, Any], mine: dict[str, Any]) -> str | None:
    """One line saying why node ``node`` cannot take part (None: it can)."""
    if theirs.get("project") is None:
        why = theirs.get("project_error", "not installed")
        return (f"node {node} ({theirs.get('hostname')}) has no swarm-coloc for its Python {theirs.get('executable')} ({why}): "
                "start its Ray from the project's venv (make setup; .venv/bin/ray start --address ...) or the project's image")
    for key, what in (("python", "Python"), ("ray", "Ray"), ("project", "swarm-coloc"), ("numpy", "numpy"), ("code", "project code")):
        if theirs.get(key) != mine.get(key):
            return (f"node {node} ({theirs.get('hostname')}) runs {what} {theirs.get(key)}, this driver {mine.get(key)}: "
                    "every node needs the same versions (the same venv or image everywhere)")
    return None

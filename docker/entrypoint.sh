#!/bin/sh
# Entry point of the swarm-coloc image (run under tini as PID 1).
#   docker run IMAGE                         -> swarm --help
#   docker run IMAGE swarm sim ...           -> any command on PATH, as given
#   docker run IMAGE sat_agent --id 3        -> python -m sat_agent --id 3
#   docker run IMAGE world_sim | selector | <recorder> | <router> ...  (same)
# A first word that is not a command but names an importable Python module is
# run as `python -m MODULE ARGS...`: every role is a module of the project.
set -e
[ $# -gt 0 ] || set -- swarm --help
case "$1" in
  -*) exec swarm "$@" ;;
  *[!A-Za-z0-9_.]*) exec "$@" ;;
esac
if ! command -v "$1" >/dev/null 2>&1 &&
   python -c 'import importlib.util, sys; sys.exit(importlib.util.find_spec(sys.argv[1]) is None)' "$1" 2>/dev/null; then
  exec python -m "$@"
fi
exec "$@"

"""Recordings: bytes as an MCAP file through swarm.record.mcaplog.iter_messages,
swarm.record.recording.load_recording (RecordingError) and recover (never an error).
``python fuzz/fuzz_mcap.py [atheris args]``."""

import sys

from _harness import fuzz

# What mcap_target imports at its first call (and mcaplog when it first reads a file): the
# reader, the loader and the mcap library itself, instrumented only if imported by fuzz().
IMPORTS = ("swarm.record.mcaplog", "swarm.record.recording", "mcap.reader", "mcap.stream_reader")

if __name__ == "__main__":
    fuzz("mcap", sys.argv[1:], include=("mcap",), imports=IMPORTS)

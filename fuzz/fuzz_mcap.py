"""Recordings: bytes as an MCAP file through swarm.record.mcaplog.iter_messages,
swarm.record.recording.load_recording (RecordingError) and recover (never an error).
``python fuzz/fuzz_mcap.py [atheris args]``."""

import sys

from _harness import fuzz

if __name__ == "__main__":
    fuzz("mcap", sys.argv[1:], include=("mcap",))

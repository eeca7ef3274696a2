"""Bus messages: ``python fuzz/fuzz_messages.py --kind est [atheris args]``; every kind of
swarmrt.bus.messages.MODELS, through the receiver's whole path (decode, validate, the key,
the conversions) and the recorder's (fuzz.targets.message_target)."""

import argparse
import sys

from _harness import fuzz

if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__, add_help=False)
    ap.add_argument("--kind", required=True, help="message kind: clock, sensors, cam, img, meas, batches, est, full_est, ...")
    a, rest = ap.parse_known_args()
    fuzz(f"msg_{a.kind}", rest, own=("--kind", a.kind))
    sys.exit(0)

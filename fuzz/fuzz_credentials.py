"""Credentials and keys files: bytes as a credential, agents.json, router.json and password
dictionary (swarmrt.security; SystemExit naming the file). ``python fuzz/fuzz_credentials.py [atheris args]``."""

import sys

from _harness import fuzz

if __name__ == "__main__":
    fuzz("credentials", sys.argv[1:])

"""Generated from proto/swarm/v1/*.proto by scripts/gen_proto.py: do not edit (the bus
messages of schema version 1; :mod:`swarm.bus.messages` is the Python face of them)."""

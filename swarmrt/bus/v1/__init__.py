"""Generated from proto/swarm/v1/*.proto by scripts/gen_proto.py: do not edit (the bus
messages of schema version 1, protobuf package ``swarm.v1``; :mod:`swarmrt.bus.messages` is
the Python face of them). They live in the runtime, beside the code that reads and writes
them, and import only protobuf and each other."""

"""The Zenoh bus: message schemas and keys (:mod:`.messages`), sessions (:mod:`.session`),
conversions between core values and messages (:mod:`.convert`)."""

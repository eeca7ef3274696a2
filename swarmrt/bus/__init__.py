"""The Zenoh bus: message schemas and keys (:mod:`.messages`), the one receive path every
reader opens a sample with (:mod:`.receive`), sessions (:mod:`.session`), conversions between
core values and messages (:mod:`.convert`), and the generated protobuf classes (:mod:`.v1`)."""

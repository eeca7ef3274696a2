"""The runtime the roles stand on: the bus (keys, messages, validation, conversion,
sessions), the protocol vocabulary, the process shell, credentials, scenario files, the
choice of measurement models, and process-wide numeric tuning.

Below it: :mod:`swarmvision` and the pure core :mod:`swarmcore`; above it: the roles
(``world_sim``, ``sat_agent``, ``selector``) and the application (:mod:`swarm`). Importing
it does nothing but define (``pyproject.toml`` holds the layers as an import contract).
"""

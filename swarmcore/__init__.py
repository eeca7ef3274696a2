"""The pure numeric core: quaternions, dynamics, sensors, the cooperative MEKF, graphs,
selection, metrics, the scenario model and the in-process simulator. Numbers in, numbers
out: no bus, no files, no configuration files, no vision libraries.

Importing it does nothing but define. The process-wide settings its numbers depend on
(one OpenBLAS kernel family, one BLAS thread, malloc thresholds) are made by each entry
point, explicitly: :func:`swarmrt.tuning.tune_process`.
"""

"""Studies: many runs of a scenario (Monte Carlo, strategy comparison, the network study) on
a local pool or a Dask cluster, and the report page."""

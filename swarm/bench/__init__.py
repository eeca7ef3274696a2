"""Benchmarks that print numbers and write JSON: the filter, the bus, a whole swarm's real-time
factor, the router's access rules, a Dask cluster, selection."""

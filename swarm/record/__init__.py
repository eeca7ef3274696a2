"""Recording: the recorder role (every bus message into MCAP), the MCAP writer and reader,
the Foxglove channels derived from a run, and reading a recording back into a run's result."""

"""A swarm over several hosts on Ray (``swarm run --cluster``): see docs/cluster.md."""

"""The selector: which relative measurements the swarm takes each step (see :mod:`selector.node`)."""

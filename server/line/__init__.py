"""A line of cells on one machine: the broker, the demo launcher, the line view."""

"""Plumbing with no knowledge of the cell: the bus, the clock, eager starts."""

"""What every layer shares: typed errors, constrained values, process helpers."""

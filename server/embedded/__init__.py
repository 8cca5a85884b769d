"""The in-process API for integrators who embed the cell in a Python program."""

"""The machine: states, events and the transition table, the pure decision, its actions."""

"""The worker, the one consumer of the event queue, and what it uses to act and record."""

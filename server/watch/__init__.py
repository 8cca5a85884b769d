"""The cell watching itself: its own resources, its links, its error rate, its parts' trends."""

"""What a support engineer asks for first, in one archive (`bundle.py`)."""

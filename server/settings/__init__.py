"""The one Settings model, how it is loaded, and what each setting means."""

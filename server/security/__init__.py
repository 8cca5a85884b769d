"""Who may do what: tokens and roles, one-shot WebSocket tickets, the access policy."""

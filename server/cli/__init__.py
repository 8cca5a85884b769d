"""Small command-line tools: backup and restore, health check, generated files."""

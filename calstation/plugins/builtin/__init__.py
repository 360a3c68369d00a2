"""calstation's built-in plugins: ordinary plugin modules registered through the same hooks."""

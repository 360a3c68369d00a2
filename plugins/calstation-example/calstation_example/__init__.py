"""Example calstation plugin: a run observer that appends JSON lines to a file."""

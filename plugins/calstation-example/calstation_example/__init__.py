"""Example calstation plugin: drivers, a fine-tuning strategy and a run observer."""

"""The pipeline: stages, the run directory, and the commands that run them."""

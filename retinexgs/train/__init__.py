"""Training of RetinexGS: losses and the optimisation loop."""

"""Ground truth: calibration of the noise model, range scales and evaluation against the truth.
Imports model to joining."""

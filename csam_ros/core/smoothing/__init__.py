"""One robot's local map: its smoother and the map as joining takes it. Imports sam and the
model."""

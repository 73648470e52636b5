"""Square-root smoothing's machinery: factors, the sparse solver and covariances (selected
inverse). Imports the model."""

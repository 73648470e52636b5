"""Independent references for tests and benchmarks (GTSAM, imported only where used)."""

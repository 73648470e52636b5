"""csam_ros: collaborative multi-robot SLAM by square-root information smoothing (C-SAM)."""

import os

# The dense algebra here works on small blocks, where a multi-threaded BLAS only adds overhead
# (measured: a 27x27 triangular solve 3.3 ms threaded vs 0.02 ms single-threaded on 2 busy
# cores). Set before numpy is first imported through this package; a user's setting wins.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

__version__ = "0.1.0"

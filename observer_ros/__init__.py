"""observer_ros: state estimators (Luenberger, reduced-order, Kalman) as ROS 2 nodes."""

import os

# Our matrices are tiny (n < 30): BLAS threads can only cost. On a loaded machine
# OpenBLAS's threads spin waiting for cores, and a 4x4 matrix exponential took 6 ms
# instead of 20 us (benchmarks/README.md, P1). Set before numpy loads OpenBLAS (the nodes
# and tools import observer_ros first); a value the user gave is kept.
os.environ.setdefault('OPENBLAS_NUM_THREADS', '1')

__version__ = '0.1.0'

"""edgepos: an edge positioning service for connected vehicles."""

import os

# Every matrix edgepos factors or multiplies is at most a few dozen wide. BLAS worker threads never
# help at that size, and under callgrind they doubled the instructions a run executed while they
# spin-waited, taking CPU from the other workers. Pin BLAS to one thread unless the operator chose
# otherwise. This only works when edgepos is imported before numpy, as in `edgepos serve` and the CLI.
for _variable in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_variable, "1")

__version__ = "0.1.0"

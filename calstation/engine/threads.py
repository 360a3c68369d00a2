"""One BLAS thread for the engine.

The engine's products are tall and thin: (N, 3) returns turned by a 3 × 3 rotation, (N, 6)
Jacobians. OpenBLAS splits each over every core and its threads spin while they wait; on a
2-core station computer that also runs the scans, the operator page and the database, they
made the cube check, the shape strategy and the periodicity fine-tuning 3–4 times slower at a
load of 6–8 than one thread, and an (N, 3) @ (3, 3) product 5 times slower (0.78 → 3.9 ms for
200 000 returns; docs/performance.md). Where parallel work pays, the engine does it itself (the
two half-turns of a spin scan side by side, the KD-trees' queries on every core).
"""

from __future__ import annotations

import os
import sys

BLAS_THREAD_VARIABLES = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")
"""What BLAS libraries read their thread count from; one set by the user is obeyed."""


def one_blas_thread() -> None:
    """Give the BLAS libraries one thread, unless the environment names a count.

    A library NumPy or SciPy loads later reads ``OPENBLAS_NUM_THREADS`` (set here for this
    process and the processes it starts); one already loaded (NumPy imported before the engine)
    is limited through threadpoolctl."""
    if any(name in os.environ for name in BLAS_THREAD_VARIABLES):
        return
    os.environ["OPENBLAS_NUM_THREADS"] = "1"
    if "numpy" in sys.modules or "scipy" in sys.modules:
        from threadpoolctl import threadpool_limits

        threadpool_limits(limits=1, user_api="blas")

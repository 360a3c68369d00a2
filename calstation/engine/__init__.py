"""The calibration engine: pure functions over arrays (docs/architecture.md).

Importing it sets the BLAS libraries NumPy and SciPy use to one thread (unless the environment
names a count): see :func:`calstation.engine.threads.one_blas_thread`.
"""

from calstation.engine.threads import one_blas_thread

one_blas_thread()

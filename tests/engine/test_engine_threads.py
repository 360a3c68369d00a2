"""The engine's BLAS runs on one thread unless the environment names a count
(calstation.engine.threads; docs/performance.md)."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

from calstation.engine.threads import BLAS_THREAD_VARIABLES

PROBE = """
import json, sys
{first}
from threadpoolctl import threadpool_info
blas = [d for d in threadpool_info() if d["user_api"] == "blas"]
print(json.dumps(sorted({{d["num_threads"] for d in blas}})))
"""


def _blas_threads(first: str, **env: str) -> list[int]:
    clean = {k: v for k, v in os.environ.items() if k not in BLAS_THREAD_VARIABLES}
    out = subprocess.run([sys.executable, "-c", PROBE.format(first=first)], env=clean | env,
                         capture_output=True, text=True, check=True).stdout
    threads: list[int] = json.loads(out.strip().splitlines()[-1])
    return threads


@pytest.mark.parametrize("first", [
    "import calstation.engine.frames; import numpy, scipy.linalg",  # the engine first
    "import numpy, scipy.linalg; import calstation.engine.frames",  # NumPy and SciPy first
    "import numpy; import calstation.engine.frames; import scipy.linalg",
])
def test_the_engine_gives_blas_one_thread(first: str) -> None:
    assert _blas_threads(first) == [1]


def test_a_thread_count_the_environment_names_is_obeyed() -> None:
    assert _blas_threads("import calstation.engine.frames; import numpy, scipy.linalg",
                         OPENBLAS_NUM_THREADS="2") == [2]

"""The torch devices tensor-touching tests run on: the CPU everywhere, CUDA where one is available.

Use ``@pytest.mark.parametrize("device", DEVICES)``. On a machine without CUDA the cuda variants are
reported as skipped (with the reason), so a CPU-only run shows that they exist and did not run.
"""

import pytest
import torch

DEVICES = [
    "cpu",
    pytest.param("cuda", marks=pytest.mark.skipif(
        not torch.cuda.is_available(), reason="no CUDA device here: the cuda variant runs where one is")),
]

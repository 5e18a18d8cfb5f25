"""Shared test configuration: hypothesis profiles and dtype tolerances.

Profiles: ``default`` (25 examples, used in CI) and ``thorough`` (200 examples): HYPOTHESIS_PROFILE=thorough.
"""

import os

import pytest
import torch
from hypothesis import HealthCheck, settings

settings.register_profile(
    "default",
    max_examples=25,
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
    derandomize=True,
)
settings.register_profile("thorough", max_examples=200, deadline=None, suppress_health_check=[HealthCheck.too_slow])
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "default"))

# Stated tolerances: float64 algebra is exact to rounding; float32 gets a looser, stated bound.
ATOL = {torch.float64: 1e-10, torch.float32: 1e-4}

torch.set_num_threads(1)  # tests run under pytest-xdist (-n 2) on 2 cores


def pytest_addoption(parser):
    parser.addoption(
        "--device",
        default="cpu",
        help="where the tests marked `device` run their float32 computations (cpu | cuda | cuda:N); they compare "
        "them with float64 on the CPU (benchmarks/gpu_check.sh runs them with --device cuda)",
    )


@pytest.fixture(scope="session")
def device(request) -> torch.device:
    """The ``--device`` of the run (tests marked ``device``); a CUDA device that is not there fails, not skips."""
    dev = torch.device(request.config.getoption("--device"))
    if dev.type == "cuda" and not torch.cuda.is_available():
        pytest.fail(f"--device {dev}: torch {torch.__version__} sees no CUDA device")
    return dev

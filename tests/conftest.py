import os

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("MPLBACKEND", "Agg")
os.environ.setdefault("WANDB_MODE", "offline")

import torch  # noqa: E402
from hypothesis import HealthCheck, settings  # noqa: E402

torch.set_num_threads(1)

# Property tests draw the same examples on every run (same code, same numbers) and have no deadline: a 2-core CI
# machine's timing jitter must not fail a property. HYPOTHESIS_PROFILE=explore draws fresh examples.
settings.register_profile("kpflow", derandomize=True, deadline=None, suppress_health_check=[HealthCheck.too_slow])
settings.register_profile("explore", derandomize=False, deadline=None, suppress_health_check=[HealthCheck.too_slow])
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "kpflow"))


import pytest  # noqa: E402


@pytest.fixture(scope="session")
def walk_store(tmp_path_factory):
    """A store of synthetic Push-T episodes in which the agent walks straight to the block
    (:func:`tests.helpers.walk_to_block_store`), for the tests that only read it."""
    from tests.helpers import walk_to_block_store

    path = tmp_path_factory.mktemp("walk") / "demos.zarr"
    walk_to_block_store(path)
    return path

from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir

import dslearn.schemas  # noqa: F401,E402  (registers the task schemas the configs name)

CONF = str(Path(__file__).resolve().parents[1] / "conf")


@pytest.fixture
def make_cfg():
    """Compose the project's Hydra config with overrides (no app, no output dir)."""

    def _make(*overrides):
        with initialize_config_dir(config_dir=CONF, version_base=None):
            return compose("config", overrides=list(overrides))

    return _make


import os

# Threads: one by default (small batched ops: one thread is fastest and avoids oversubscription).
# CI's second, numerical pass sets DSLEARN_TEST_THREADS=2 (with ATEN_CPU_CAPABILITY=default, the
# generic kernels): then every torch.set_num_threads call of the code under test is pinned to that
# count too, so a threshold that holds only on one CPU's kernel path or one thread count fails in CI.
_THREADS = int(os.environ.get("DSLEARN_TEST_THREADS", "1"))

# The parsed-data cache (dslearn.data.cache) of the tests' runs goes to a folder of this test session, not the
# user's ~/.cache/dslearn (subprocesses inherit it); a test of the cache sets its own.
if "DSLEARN_CACHE_DIR" not in os.environ:
    import tempfile

    os.environ["DSLEARN_CACHE_DIR"] = tempfile.mkdtemp(prefix="dslearn-test-cache-")
torch.set_num_threads(_THREADS)
if "DSLEARN_TEST_THREADS" in os.environ:
    _set = torch.set_num_threads
    torch.set_num_threads = lambda n: _set(_THREADS)  # noqa: E731


@pytest.fixture(autouse=True)
def _seed():
    torch.manual_seed(0)

from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir

CONF = str(Path(__file__).resolve().parents[1] / "conf")


@pytest.fixture
def make_cfg():
    """Compose the project's Hydra config with overrides (no app, no output dir)."""

    def _make(*overrides):
        with initialize_config_dir(config_dir=CONF, version_base=None):
            return compose("config", overrides=list(overrides))

    return _make


torch.set_num_threads(1)  # small batched ops: one thread is fastest and avoids oversubscription


@pytest.fixture(autouse=True)
def _seed():
    torch.manual_seed(0)

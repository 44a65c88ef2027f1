"""Shared fixtures: the ERC assets in ../shared (optional), seeded RNGs; property tests derandomized
(the same examples on every run: a seeded process, like the rest; ``HYPOTHESIS_PROFILE=explore``
searches afresh)."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest
from hypothesis import settings

settings.register_profile("seeded", derandomize=True)
settings.register_profile("explore", derandomize=False)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "seeded"))

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared"
ERC = SHARED / "data" / "erc_marsyard"


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(12345)


@pytest.fixture(scope="session")
def erc_dir() -> Path:
    """Path to the ERC Mars-yard assets; skips with a clear message when ../shared is absent."""
    if not ERC.is_dir():
        pytest.skip(f"ERC Mars-yard assets not found at {ERC} (../shared is absent)")
    return ERC

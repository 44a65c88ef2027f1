"""Shared fixtures: the ERC assets in ../shared (optional), seeded RNGs."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

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

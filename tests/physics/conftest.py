"""Fixtures for the physics tests."""

from __future__ import annotations

import pytest
from physics_scan_helpers import PAPER_KAPPA_US, Scan, scan_object


@pytest.fixture(scope="session")
def paper_scans() -> dict[str, Scan]:
    """Default-tier (auto) scans of plane, pole and rod at 1.5 m, seeded."""
    return {name: scan_object(k, "auto", seed=7 + i)
            for i, (name, k) in enumerate(PAPER_KAPPA_US.items())}

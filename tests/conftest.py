"""Session fixtures: seeded simulated strips with known truth."""

from __future__ import annotations

import pytest

from seqat.simulate import SimulatedFlight, StripSimConfig, simulate_strip

#: A short strip with the paper's camera and flight (60 images ~ 30 s of flight).
SHORT_STRIP = StripSimConfig(n_images=60, n_points=48)


@pytest.fixture(scope="session")
def short_strip() -> SimulatedFlight:
    return simulate_strip(SHORT_STRIP, seed=11)

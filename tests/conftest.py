"""Shared fixtures: the shipped profiles."""

from __future__ import annotations

import pytest

from lfcam import load_profile


@pytest.fixture(params=["system1", "system2"])
def profile(request):
    """Each shipped profile, as shipped (focus 3.5 m)."""
    return load_profile(request.param)

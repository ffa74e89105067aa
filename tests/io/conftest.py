import pytest
from io_testlib import REALDATA


@pytest.fixture
def realdata():
    """Folder of the real Lytro files; skips when absent."""
    if not REALDATA.is_dir():
        pytest.skip(f"real Lytro files not present at {REALDATA}")
    return REALDATA

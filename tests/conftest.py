from pathlib import Path

import pytest

SPANNER = Path(__file__).resolve().parents[2] / "shared" / "data" / "spanner"


@pytest.fixture(scope="session")
def spanner_dir() -> Path:
    """The real Fort Valley clips; tests using it skip only when the shared data folder is absent."""
    if not SPANNER.is_dir():
        pytest.skip("shared/data/spanner not present")
    return SPANNER

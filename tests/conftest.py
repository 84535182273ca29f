from pathlib import Path

import pytest

from plotmosaic.simulate.run import simulate

SHARED = Path(__file__).resolve().parents[2] / "shared" / "data"
SPANNER = SHARED / "spanner"
E57_DIR = SHARED / "e57"


@pytest.fixture(scope="session")
def e57_dir() -> Path:
    """The shared E57 samples; tests using them skip only when the folder is absent."""
    if not E57_DIR.is_dir():
        pytest.skip("shared/data/e57 not present")
    return E57_DIR


@pytest.fixture(scope="session")
def spanner_dir() -> Path:
    """The real Fort Valley clips; tests using it skip only when the shared data folder is absent."""
    if not SPANNER.is_dir():
        pytest.skip("shared/data/spanner not present")
    return SPANNER


@pytest.fixture(scope="session")
def small_sim(tmp_path_factory):
    """The `small` simulated plot (5 TLS scans in the paper layout + an ALS tile), seed 0, shared by all tests."""
    return simulate(tmp_path_factory.mktemp("sim"), "small", seed=0)

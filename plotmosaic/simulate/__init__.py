"""Forest plot simulator: terrain, trees, understory; TLS and ALS scans by ray casting; ground truth."""

from plotmosaic.simulate.config import PRESETS, SimulationConfig, make_config
from plotmosaic.simulate.run import SimulationResult, simulate

__all__ = ["PRESETS", "SimulationConfig", "SimulationResult", "make_config", "simulate"]

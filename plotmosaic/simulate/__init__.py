"""Forest plot simulator: terrain, trees, understory; TLS and ALS scans by ray casting; ground truth.

The package imports only its settings, so `plotmosaic.config.simulate` stays a leaf; the ray caster
is `plotmosaic.simulate.run` (`simulate`, `make_config`, `SimulationResult`).
"""

from plotmosaic.config.simulate import PRESETS, SimulationConfig

__all__ = ["PRESETS", "SimulationConfig"]

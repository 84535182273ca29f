"""Forest plot simulator: terrain, trees, understory; TLS and ALS scans by ray casting; ground truth.

The package's settings are `plotmosaic.config.simulate`, a leaf; the ray caster is
`plotmosaic.simulate.run` (`simulate`, `make_config`, `SimulationResult`).
"""

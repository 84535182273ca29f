"""The paper's evaluation protocol (`plotmosaic bench`): seeded trials, baselines, RMSE tables, plots."""

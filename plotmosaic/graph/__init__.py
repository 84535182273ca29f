"""Plot and region registration: candidate pairs, a resumable pair cache, parallel execution,
the GTSAM pose graph, ALS anchors and the report (`register-plot`, `tie-to-als`)."""

"""The commands' stages: register-plot (plan -> place -> grow -> solve), tie-to-als, merge."""

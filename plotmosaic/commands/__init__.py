"""One module per CLI subcommand; each stays a thin layer over the library."""

"""Pictures and an index page for a registration (`plotmosaic report`)."""

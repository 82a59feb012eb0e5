"""lcv-replay tests (a package, so that test folders such as tests/recorders never shadow the top-level packages)."""

"""Metrics, plots, reports, simulation, benchmarks and the ddfuse command line."""

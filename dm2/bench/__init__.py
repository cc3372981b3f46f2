"""Bench: score monitoring runs against the twin's injected-fault truth, suites, sweeps."""

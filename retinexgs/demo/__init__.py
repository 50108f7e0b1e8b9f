"""Synthetic demo scenes (analytic ray caster) for tests and quick runs."""

"""Shared test settings: property-based tests are derandomized to check the same cases each run."""

from hypothesis import settings

settings.register_profile("deterministic", derandomize=True, deadline=None, max_examples=60)
settings.load_profile("deterministic")

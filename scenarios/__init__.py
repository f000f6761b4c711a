"""Bundled scenarios, installed as the data package ``mjxdiff._scenarios`` (see pyproject.toml)."""

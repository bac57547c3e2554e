"""Airframe configurations shipped with the package, found by name: ``--config hfb320``.

Installed as ``gcs_estimator.configs`` (pyproject.toml maps this directory there).
"""

"""`python -m gcs_estimator`: the gcs-estimator command."""

from gcs_estimator.cli import entrypoint

entrypoint()

"""Deployment: Prefect deployments and triggers (``prefect``), Dask cluster specs (``clusters``)."""

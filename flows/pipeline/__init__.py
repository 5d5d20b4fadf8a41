"""The pipeline: planning (``plan``), the Prefect flows that run units (``run``), the frame fan-out
to Dask from inside a stage (``parallel``) and where flows run (``runtime``)."""

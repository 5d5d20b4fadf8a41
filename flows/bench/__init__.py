"""`mobileocc bench`: the pipeline benchmark (``pipeline``) and the kernel benchmarks it calls
(``fit``, ``occupancy``, ``storage``)."""

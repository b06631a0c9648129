"""The engine: configs, the plan, execution and the artifact store, below every front end.

Layers, each importing only the ones below it (``tests/pipeline/test_layers.py`` enforces it)::

    front ends   pipeline/*.py: polyvec, polyvec-inspect, polyvec-bench, polyvec-train, the page
    execute      pipeline.engine.execute: run_batch, the in-process and dask executors, one task (node)
                 pipeline.engine.kernels: numba kernels shipped compiled, first-run warm-ups
    plan         pipeline.engine.registry (the stages, the DAG), plan (tasks and keys), edits, lookup
    config       pipeline.engine.config (schemas), compose (Hydra composition, the config cache)
    store        pipeline.engine.store: the content-addressed artifact store
    stages       stages/: the algorithms, pure functions of arrays

Nothing here imports a front end. docs/ARCHITECTURE.md follows one drawing through the layers.
"""

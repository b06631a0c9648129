"""The Hydra configs of polyvec (``pkg://conf``), one group per stage + runtime, train and bench.

Hydra imports this package before it composes any of its configs; importing it registers the
structured configs (:mod:`pipeline.engine.config`) that the app configs name as ``<group>_schema``, so every
composition — the commands, ``hydra.compose`` in tests and scripts — checks the YAML against them.
"""

import pipeline.engine.config

pipeline.engine.config.register()   # the <group>_schema structured configs

"""The algorithms of polyvec, one module (or subpackage) per stage.

Stages are pure functions of arrays: they never read files, configs or stores. Each stage module
exposes ``STAGE_VERSION`` (bump when results change) and ``run(cfg, **inputs) -> Artifact`` where
``cfg`` is a plain ``dict`` (the stage's own Hydra config section) and every input is the
:class:`~stages.artifact.Artifact` of an upstream stage, passed by that stage's name.
See ``stages/INTERFACES.md`` for what every artifact holds.
"""

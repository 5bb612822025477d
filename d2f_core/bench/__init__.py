"""Benchmarks behind ``d2f-bench`` (``python -m d2f_core.bench``): the renderer's speed
(:mod:`.render`), speed against accuracy (:mod:`.accuracy`, its scenes and
metrics in :mod:`.cases`, its charts in :mod:`.charts`), peer renderers (:mod:`.peers`)
and the depth sources.

Nothing on the inference path imports this package.
"""

"""Frozen copies of modules as they were at a named commit, kept for benchmarks that time
today's code against them in the same run (``python -m d2f_core.bench render``).

``rendering.py``: ``d2f_core/rendering.py`` at commit 00e22a4, with its imports made relative
to the package. Not part of the API; never edited.
"""

"""Depth, from any source to the renderer's disparity: the sources (:mod:`.sources`: phone depth,
a file, the D2F network, Hugging Face models) and the edge refinement (:mod:`.refine`).
"""

"""Depth, from any source to the renderer's disparity: the sources (:mod:`.sources`: phone depth,
a file, the D2F network, Hugging Face models), the edge refinement (:mod:`.refine`) and the
subject finding that gives a photo its first focus (:mod:`.subject`).
"""

"""File input and output for d2f: the only part of the package that touches files.

* :mod:`.image`: photos in (JPEG, PNG 8/16-bit, TIFF, WebP, HEIC) and out.
* :mod:`.depth`: depth/disparity maps (PNG, ``.npy``, PFM, float TIFF, read by
  :mod:`.depth_files`), hole filling (:mod:`.holes`), normalisation to disparity in [0, 1]
  (1 = nearest).
* :mod:`.embedded`: phone depth embedded in photos (Google Lens Blur XMP, Apple portrait
  MPO, Apple HEIC) and :func:`load_photo`, which combines all of it.
"""

from .depth import (
    depth_to_disparity,
    fill_holes,
    load_depth,
    normalize_disparity,
    read_depth_array,
    read_pfm,
    save_depth,
    write_pfm,
)
from .embedded import Photo, extract_xmp, jpeg_segments, load_photo, read_embedded_depth
from .formats import apply_orientation
from .image import READ_EXTENSIONS, SAVE_FORMATS, ImageInfo, load_image, load_image_with_info
from .masks import load_mask
from .save import float_to_uint8, same_file, save_image

__all__ = [
    "READ_EXTENSIONS",
    "SAVE_FORMATS",
    "ImageInfo",
    "Photo",
    "apply_orientation",
    "depth_to_disparity",
    "extract_xmp",
    "fill_holes",
    "float_to_uint8",
    "jpeg_segments",
    "load_depth",
    "load_image",
    "load_image_with_info",
    "load_mask",
    "load_photo",
    "normalize_disparity",
    "read_depth_array",
    "read_embedded_depth",
    "read_pfm",
    "same_file",
    "save_depth",
    "save_image",
    "write_pfm",
]

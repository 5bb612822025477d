"""Which photos depth training never sees: about one in ten, fixed by a hash of the name.

Shared by stage 0 (:mod:`.depth_train`), the photo scenes of :mod:`.synth.photo` and the depth
bench, so that none of them imports another for it.
"""

from __future__ import annotations

import zlib

from .teachers import Photo

__all__ = ["HELDOUT_MODULUS", "is_heldout", "is_heldout_key"]

#: one photo in HELDOUT_MODULUS is held out (by a CRC of its key)
HELDOUT_MODULUS = 10


def is_heldout_key(key: str) -> bool:
    """:func:`is_heldout` for a photo known only by its :attr:`~.teachers.Photo.key`."""
    return zlib.crc32(key.encode()) % HELDOUT_MODULUS == 0


def is_heldout(photo: Photo) -> bool:
    """True for the photos that depth training never sees (about one in ten, fixed by name)."""
    return is_heldout_key(photo.key)

"""Which server files a client may make the app open: Gradio's own uploads and the samples.

The photo and depth inputs are taken raw (``preprocess=False``), so Gradio does not check
their payloads, and a client can put any path in them. :class:`UploadGate` lets through only
a regular file that Gradio stored itself (an upload to this server or a file the app or its
examples put in Gradio's cache, inside its cache folder) or a bundled sample, and refuses
everything else with one message that says nothing about the path: whether it exists, is a
folder or is a device reads the same.
"""

from __future__ import annotations

import os
import stat
from collections.abc import Iterable
from pathlib import Path
from typing import Any

__all__ = ["NOT_AN_UPLOAD", "UploadGate"]

#: the one answer to a path that is not an upload of this server
NOT_AN_UPLOAD = "This file is not an upload of this page. Please upload the photo again."
#: no path Gradio writes is longer than this
_MAX_PATH = 4096


def _inside(path: str, folder: str) -> bool:
    return path == folder or path.startswith(folder.rstrip(os.sep) + os.sep)


class UploadGate:
    """Checks the file paths that the client's payloads name.

    Args:
        samples: folders whose regular files any client may open (the bundled samples).
        cache_dir: Gradio's upload and cache folder (default: ``gradio.utils.get_upload_folder``).

    Until :meth:`bind` gives it the app's ``gr.Blocks``, no cached file is known, so only the
    samples pass.
    """

    def __init__(self, samples: Iterable[str | Path] = (), cache_dir: str | Path | None = None):
        if cache_dir is None:
            from gradio.utils import get_upload_folder

            cache_dir = get_upload_folder()
        self.cache_dir = os.path.realpath(cache_dir)
        self.samples = [os.path.realpath(s) for s in samples]
        self._blocks: Any = None

    def bind(self, blocks: Any) -> None:
        """Take the files that ``blocks`` (a ``gr.Blocks``) has stored as the known ones."""
        self._blocks = blocks

    def _stored(self, path: str, real: str) -> bool:
        """Whether Gradio recorded ``path`` as a file it wrote (uploads, cached outputs)."""
        if self._blocks is None or not _inside(real, self.cache_dir):
            return False
        for files in list(getattr(self._blocks, "temp_file_sets", ())):
            for name in list(files):
                if str(name) in (path, real):
                    return True
        return False

    def allows(self, path: Any) -> bool:
        """Whether ``path`` names a regular file that a client may make the app open."""
        if not isinstance(path, str) or not path or len(path) > _MAX_PATH or "\0" in path:
            return False
        if not os.path.isabs(path):
            return False
        real = os.path.realpath(path)
        known = self._stored(path, real) or any(_inside(real, s) for s in self.samples)
        if not known:
            return False
        try:
            return stat.S_ISREG(os.stat(real).st_mode)
        except OSError:
            return False

    def check(self, path: str) -> str:
        """``path`` when :meth:`allows` it.

        Raises:
            PermissionError: with :data:`NOT_AN_UPLOAD`, whatever the reason.
        """
        if not self.allows(path):
            raise PermissionError(NOT_AN_UPLOAD)
        return path

"""Downloads: the latest full-resolution render written to a PNG or JPEG file for the
download button.
"""

from __future__ import annotations

import os
from typing import Any

import gradio as gr
import numpy as np

from app import imaging
from app.reporting import user_error
from app.sessions import Session, prune_files, reported
from app.settings import FORMATS, RenderParams


class DownloadEvents:
    """The download event of a :class:`~app.handlers.RefocusApp`: the latest full render
    written to a file, rendered at full resolution when the page shows it at the screen's
    size."""

    @reported
    def download(self, session: Session | None, fmt: str = "PNG", shown: Any = None) -> Any:
        """Write the latest full-resolution render to a file for the download button.

        ``shown``: the status line the page shows, where the event follows a render: the
        button is left as it is unless the page shows that full render (a preview whose
        picture reached the page after it keeps the button disabled; :meth:`settle` sends
        the full render again, and its download enables it).

        Returns:
            a ``gr.DownloadButton`` update with the file (or ``gr.skip()`` without a render).
        """
        fmt = str(fmt).upper()
        if fmt not in FORMATS:
            raise user_error(f"Download format must be PNG or JPEG, got {fmt!r}.")
        if session is None:
            return gr.update(value=None, label="Download", interactive=False)
        session.touch()
        with session.lock:
            params = session.last_full_params
            if params is None or session.full_params != params:
                return gr.skip()  # no full render, or a preview is shown
            if shown is not None and not session.shows_last_full(shown):
                return gr.skip()  # the page shows another picture
            done = session.download_file
            written = done is not None and done[:2] == (params, fmt) and done[2].exists()
        if written:  # hand out the same file
            w, h = session.size
            label = f"Download {fmt} ({w}x{h})"
            return gr.update(value=str(done[2]), label=label, interactive=True)
        # the full resolution, rendered now when the page shows it at the screen's size
        image = self.full_res_picture(session, params)
        if image is None:
            return gr.skip()
        # each file in its own numbered folder, written once: a file handed to Gradio is
        # never rewritten or removed while it may still be copied (see prune_files)
        root = self._session_dir(session, "download")
        folder = root / self._next_name(session, "")
        folder.mkdir()
        ext = "png" if fmt == "PNG" else "jpg"
        name = f"{session.name}_bokeh_{self._file_params(params)}.{ext}"
        path = imaging.save_image(
            image, folder / name, icc_profile=session.icc_profile, exif=session.exif
        )
        prune_files(root, 2)
        with session.lock:
            if session.last_full_params != params or session.full_params != params:
                return gr.skip()  # a newer render came in while this file was written
            session.download_file = (params, fmt, path)
        h, w = image.shape[:2]
        return gr.update(value=str(path), label=f"Download {fmt} ({w}x{h})", interactive=True)

    def _keep_full_res(self, session: Session, params: RenderParams, bokeh: np.ndarray) -> None:
        """Keep the full-resolution picture of ``params`` on disk for the download, not in
        memory (call with the session's lock held)."""
        folder = self._session_dir(session, "")
        part = folder / "last_full.part.npy"
        np.save(part, bokeh)
        os.replace(part, folder / "last_full.npy")
        session.full_res_params = params

    def full_res_picture(self, session: Session, params: RenderParams) -> np.ndarray | None:
        """The full-resolution picture of ``params``, the shown render's: read from disk, or
        rendered now (the page shows it at the screen's size); ``None`` when the page has
        moved on to other values meanwhile."""
        with session.lock:
            image = session.last_full if session.full_res_params == params else None
        if image is not None:
            return image
        scene = session.scene
        result = self.model.render(scene, params.focus, params.blur, **params.render_options())
        del scene
        bokeh = imaging.to_uint8(result.bokeh)
        with session.lock:
            if session.last_full_params != params or session.closed:
                return None
            self._keep_full_res(session, params, bokeh)
        return bokeh

"""The summary line over the status line, which waits closed behind "Advanced": the picture
the page shows in a photographer's words (where the focus is, the aperture, what is sharp from
near to far, the paint), or the error."""

from __future__ import annotations

from typing import Any

from app.sessions import Session


def summary_line(session: Session | None, status: Any = None) -> str:
    """The picture the page shows in a photographer's words: where the focus is, the
    aperture, what is sharp (the depth whose blur stays under a pixel: the focal range
    and half a pixel's worth of blur on each side of it), and the paint. Empty without
    a photo. An error is said here as the status line says it, since the status line waits
    closed behind "Advanced"."""
    if str(status or "").startswith("Error"):
        return "**Error**" + str(status)[len("Error") :]
    if not isinstance(session, Session) or session.closed or not status:
        return ""
    with session.lock:
        params = session.wanted or session.last_full_params
        brushes = session.brushes
    if params is None:
        return ""
    at = round(100 * params.position)
    if params.f_number is None:
        return f"**Focus** {at} % of the way back · **no blur**: the photo as it is"
    half = params.focal_range / 2 + (1.0 / params.blur if params.blur > 0 else 1.0)
    near = round(100 * max(0.0, params.position - half))
    far = round(100 * min(1.0, params.position + half))
    text = (
        f"**Focus** {at} % of the way back · **aperture** f/{params.f_number:g} · "
        f"**sharp** from {near} % to {far} % of the way back (0 % the nearest thing, "
        "100 % the farthest)"
    )
    if brushes is not None and params.paint:
        sharp, blurred = brushes.coverage()
        text += f" · **painted**: {100 * sharp:.0f} % kept sharp, {100 * blurred:.0f} % blurred"
    return text

"""What the app tells a user: a ``gr.Error`` toast for an expected error, one line for the
server log, and the messages and updates the events share.
"""

from __future__ import annotations

from typing import Any

import gradio as gr


def user_error(message: str) -> gr.Error:
    """A ``gr.Error`` for the user's toast; expected, so no traceback in the server log."""
    return gr.Error(message, print_exception=False)


def one_line(message: Any, limit: int = 300) -> str:
    """A message on one line of at most ``limit`` characters, for the server log."""
    text = " ".join(str(message).split())
    return text if len(text) <= limit else text[: limit - 3] + "..."


#: What an event on a closed session answers.
CLOSED_MESSAGE = (
    "This photo was closed to free memory (unused for a while, or the page was closed); "
    "please upload it again."
)

#: What an event on a session closed for another user's photo answers.
MADE_ROOM_MESSAGE = (
    "This photo was closed to make room for another photo (the server keeps a limited "
    "number open at once); please upload it again."
)


SKIP4 = (gr.skip(), gr.skip(), gr.skip(), gr.skip())


#: An event that needs a photo in a session that has none.
NO_PHOTO = "Upload a photo first: no photo is loaded in this session."

#: The download button while a preview is shown: nothing that matches the screen to save.
DOWNLOAD_WAIT = {"__type__": "update", "interactive": False}

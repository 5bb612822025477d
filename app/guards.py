"""What the server answers to requests that no page sends: a forged or malformed request is
refused with one clear error and one log line, never a traceback (see app/README.md,
"Requests that no page sends")."""

from __future__ import annotations

import logging
from typing import Any

import gradio as gr

from app.reporting import one_line

__all__ = ["refuse_bad_requests", "refuse_unknown_event", "request_fault", "request_cut_short"]

# the app's own log: these are its messages
log = logging.getLogger("app.main")


def request_fault(err: BaseException) -> str:
    """One line naming what was wrong with a request that Gradio refused before any handler
    ran (a file path that was not uploaded, a value of the wrong type, too few inputs)."""
    errors = getattr(err, "errors", None)
    if callable(errors):  # pydantic's ValidationError: the first field and what it got
        try:
            first = errors()[0]
            got = type(first.get("input")).__name__
            text = f"{getattr(err, 'title', 'input')}: {first.get('msg', err)} (got {got})"
        except (IndexError, TypeError, AttributeError):
            text = str(err)
    else:
        text = str(getattr(err, "message", None) or err) or type(err).__name__
        lines = [line.strip() for line in text.splitlines() if line.strip()]
        # Gradio's ComponentProcessingError says what it expected on a line of its own
        expected = [line for line in lines if line.startswith("Expected")]
        text = (expected or lines or [type(err).__name__])[0]
    text = " ".join(text.replace("`", "").split())
    return text if len(text) <= 300 else text[:297] + "..."


def refuse_bad_requests(demo: gr.Blocks) -> None:
    """Make Gradio's checks of a request's inputs end in one log line and a clear error.

    Before a handler runs, Gradio checks each input: a file must have been uploaded to this
    server, a value must fit its component (a number for a slider, one of the choices of a
    radio). A forged or malformed request fails there, and Gradio printed the whole
    traceback to the server log and sent the caller no message. Here such a request is
    refused with ``gr.Error("Invalid request: <reason>")`` and one warning line
    (``refused a request to /load: <reason>``). Failures inside the handlers are theirs to
    report (:func:`app.handlers.reported`).
    """
    check = demo.preprocess_data

    async def preprocess_data(block_fn, *args, **kwargs):
        try:
            return await check(block_fn, *args, **kwargs)
        except gr.Error as err:
            if not err.print_exception:
                raise
            reason = request_fault(err)
        except Exception as err:
            reason = request_fault(err)
        name = getattr(block_fn, "api_name", None) or getattr(block_fn, "name", "?")
        log.warning("refused a request to /%s: %s", name, reason)
        raise gr.Error(f"Invalid request: {reason}", print_exception=False) from None

    # the instance attribute shadows the method that Blocks.process_api calls
    demo.preprocess_data = preprocess_data


async def refuse_unknown_event(request: Any, err: Exception) -> Any:
    """Exception handler of the web server for a request that names no event: an API name
    that does not exist, or a function index out of range (Gradio raises there, and the
    server printed the traceback). The caller gets 404 and the reason; one line is logged.
    Any other ``KeyError`` is a fault of the server and keeps its traceback in the log."""
    from fastapi.responses import JSONResponse

    path = request.url.path
    if isinstance(err, KeyError) and not path.endswith("/queue/join"):
        log.error("failure at %s", path, exc_info=err)
        return JSONResponse({"error": "Internal server error"}, status_code=500)
    if isinstance(err, KeyError):
        reason = f"no event with function index {one_line(err.args[0] if err.args else '')}"
    else:
        reason = request_fault(err)
    log.warning("refused a request to %s: %s", path, reason)
    return JSONResponse({"error": f"Invalid request: {reason}"}, status_code=404)


async def request_cut_short(request: Any, err: Exception) -> Any:
    """Exception handler of the web server for a request whose body ended before its declared
    length (the client closed the connection mid-upload, or sent less than its
    ``Content-Length`` says): one line in the log, no traceback. Nobody is left to read
    the answer."""
    from fastapi.responses import PlainTextResponse

    client = getattr(request, "client", None)
    who = f" from {client.host}" if client is not None else ""
    log.warning(
        "a request to %s%s ended before its declared length (the client disconnected)",
        request.url.path, who,
    )  # fmt: skip
    return PlainTextResponse("request body cut short", status_code=400)

"""The D2F refocusing web app (Gradio): the page and the ``d2f-app`` CLI.

Start it with ``d2f-app`` or ``python -m app`` (http://127.0.0.1:7860). The page's panels are
built in :mod:`app.panels` and connected in :mod:`app.wiring`; the logic lives in
:mod:`app.handlers`; rendering and click-to-focus are done by ``d2f_core.pipeline.D2F``.
"""

from __future__ import annotations

import argparse
import logging
import os
from types import SimpleNamespace
from typing import Any

import gradio as gr
from gradio.route_utils import FnIndexInferError
from starlette.requests import ClientDisconnect

from app import imaging
from app import sources as depth_choice
from app.cache import SceneCache
from app.guards import refuse_bad_requests, refuse_unknown_event, request_cut_short
from app.handlers import RefocusApp
from app.panels import (
    SAMPLES_DIR,
    brush_panel,
    depth_panels,
    input_panel,
    lens_controls,
    result_panel,
)
from app.sessions import delete_session
from app.uploads import UploadGate
from app.wiring import Wiring
from d2f_core.depth import sources as depth_sources

log = logging.getLogger(__name__)

#: Events that run the model share one concurrency group of this many parallel calls
#: (all sessions together); on a 2-core CPU more only adds contention.
DEFAULT_CONCURRENCY = 4
#: Gradio drops a session's state this long (seconds) after it was last set; the app
#: closes idle sessions itself, sooner (``D2F_APP_SESSION_IDLE_S``, app/handlers.py).
SESSION_TTL_S = 3600
#: Uploads larger than this many MB are refused by Gradio (``D2F_APP_MAX_UPLOAD_MB``).
DEFAULT_MAX_UPLOAD_MB = 100
#: The interfaces that only this computer reaches (``--allow-any-depth-model`` needs one).
LOCAL_HOSTS = ("127.0.0.1", "localhost", "::1")
#: Page states (one per browser tab or API client) Gradio keeps, oldest dropped first
#: (its default is 10000); each holds a copy of the page's component settings.
STATE_SESSIONS = 1000

CSS = """
#result img, #input img { object-fit: contain; }
.d2f-legend { padding: 2px 6px; }
"""

#: Gradio's slider sends ``release`` (the full render) only on pointer-up over the track and
#: when its number box loses focus. This page script ends the other ways of setting a value
#: the same way: arrow / Home / End / Page keys on a focused slider (on key-up, so a held key
#: renders once) and Enter in the number box. It sends the pointer-up that Gradio listens to.
RELEASE_JS = """
() => {
    const keys = new Set(["ArrowLeft", "ArrowRight", "ArrowUp", "ArrowDown", "Home", "End",
                          "PageUp", "PageDown"]);
    const release = (el) => el.dispatchEvent(new PointerEvent("pointerup", {bubbles: true}));
    document.addEventListener("keyup", (e) => {
        const el = e.target;
        if (el instanceof HTMLInputElement && el.dataset.testid === "range-input"
            && keys.has(e.key)) release(el);
    }, true);
    document.addEventListener("keydown", (e) => {
        const el = e.target;
        if (el instanceof HTMLInputElement && el.dataset.testid === "number-input"
            && e.key === "Enter" && !e.repeat) release(el);
    }, true);
}
"""

INTRO = """# D2F refocus
Upload a photo, then **click where it should be sharp**, or set focus and aperture below.
Dragging a slider shows a quick preview; releasing it renders at full resolution.
"""


def load_model(weights: str | os.PathLike | None = None) -> Any:
    """``D2F.from_pretrained`` with an optional weights path (else env ``D2F_WEIGHTS``)."""
    from d2f_core.pipeline import D2F

    if weights is not None:
        return D2F.from_pretrained(weights)
    return D2F.from_pretrained()


def build_demo(
    model: Any = None,
    *,
    weights: str | os.PathLike | None = None,
    cache: SceneCache | None = None,
    concurrency: int | None = None,
) -> gr.Blocks:
    """Build the app.

    Args:
        model: a ``D2F`` instance; None loads ``D2F.from_pretrained(weights)``.
        weights: checkpoint path used when ``model`` is None (default: env ``D2F_WEIGHTS``,
            then ``assets/weights/d2f_lite.pt``).
        cache: scene cache (default: the process-wide :data:`app.cache.SCENE_CACHE`).
        concurrency: parallel model calls across all sessions (default
            ``D2F_APP_CONCURRENCY`` or 4).

    Returns:
        the ``gr.Blocks`` app, queue configured, not launched.
    """
    if model is None:
        model = load_model(weights)
    if concurrency is None:
        concurrency = int(os.environ.get("D2F_APP_CONCURRENCY", DEFAULT_CONCURRENCY))
    # the photo and depth inputs are taken raw: only Gradio's own uploads and the samples
    # may be opened (app/uploads.py)
    files = UploadGate([SAMPLES_DIR])
    logic = RefocusApp(model, cache, files=files)

    with gr.Blocks(title="D2F refocus", delete_cache=(600, 3600)) as demo:
        session = gr.State(None, time_to_live=SESSION_TTL_S, delete_callback=delete_session)
        gr.Markdown(INTRO)
        with gr.Row():
            with gr.Column(scale=1):
                page = SimpleNamespace(**vars(input_panel()), **vars(lens_controls()))
                page.__dict__.update(vars(brush_panel()), **vars(depth_panels()))
            with gr.Column(scale=1):
                page.__dict__.update(vars(result_panel()))
        page.session = session
        events = Wiring(page, logic, concurrency, files)
        events.loading()
        events.renders()
        events.clicks()
        events.paint()
        events.loupe()
        events.views()

        # a closed tab frees its photo at once (API clients' sessions expire when idle)
        def end_session(request: gr.Request):
            logic.end_sessions(getattr(request, "session_hash", None))

        demo.unload(end_session)
    refuse_bad_requests(demo)
    files.bind(demo)
    demo.queue(default_concurrency_limit=concurrency)
    return demo


def launch_options() -> dict[str, Any]:
    """Keyword arguments of ``demo.launch`` that the app needs besides host and port: the
    page script (:data:`RELEASE_JS`), the style sheet, the examples' folder, the upload
    limit (``D2F_APP_MAX_UPLOAD_MB``, default 100), how many sessions' page state Gradio
    keeps (:data:`STATE_SESSIONS`) and the server's answers to a request for an event that
    does not exist (:func:`refuse_unknown_event`) and to an upload cut short
    (:func:`request_cut_short`)."""
    upload_mb = os.environ.get("D2F_APP_MAX_UPLOAD_MB", str(DEFAULT_MAX_UPLOAD_MB))
    return {
        "js": RELEASE_JS,
        "css": CSS,
        "allowed_paths": [str(SAMPLES_DIR)],
        "max_file_size": int(float(upload_mb) * (1 << 20)),
        "state_session_capacity": STATE_SESSIONS,
        "app_kwargs": {
            "exception_handlers": {
                FnIndexInferError: refuse_unknown_event,
                KeyError: refuse_unknown_event,
                ClientDisconnect: request_cut_short,
            }
        },
    }


def main(argv: list[str] | None = None) -> int:
    """``d2f-app``: serve the app (default http://127.0.0.1:7860)."""
    parser = argparse.ArgumentParser(prog="d2f-app", description=__doc__.splitlines()[0])
    parser.add_argument(
        "--host", default="127.0.0.1", help="interface to bind (default: %(default)s)"
    )
    parser.add_argument("--port", type=int, default=7860, help="port (default: %(default)s)")
    parser.add_argument(
        "--weights",
        default=None,
        help="checkpoint (default: $D2F_WEIGHTS, else assets/weights/d2f_lite.pt)",
    )
    parser.add_argument(
        "--threads",
        type=int,
        default=int(os.environ.get("D2F_APP_THREADS", "1")),
        help="torch threads per render (default: $D2F_APP_THREADS or 1; see app/README.md)",
    )
    parser.add_argument(
        "--depth-models",
        default=os.environ.get("D2F_APP_DEPTH_MODELS", ""),
        metavar="ID,...",
        help="Hugging Face depth models that clients may pick (hub ids or folders, comma "
        "separated; each must be in the local Hugging Face cache: the app never downloads "
        "one). Default: $D2F_APP_DEPTH_MODELS, else none",
    )
    parser.add_argument(
        "--allow-any-depth-model",
        action="store_true",
        help="let clients also name any hub id or folder on this computer (local use only: "
        "refused unless --host is 127.0.0.1, localhost or ::1)",
    )
    args = parser.parse_args(argv)
    if args.threads < 1:
        parser.error(f"--threads must be >= 1, got {args.threads}")
    if args.allow_any_depth_model and args.host not in LOCAL_HOSTS:
        parser.error(
            f"--allow-any-depth-model is for local use only; it cannot be used with "
            f"--host {args.host} (use --depth-models ID,... to offer models to others)"
        )
    try:
        models = depth_choice.parse_models(args.depth_models)
    except ValueError as err:
        parser.error(f"--depth-models: {err}")
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    logging.getLogger("httpx").setLevel(logging.WARNING)
    import torch

    # several renders run at once (one per session event); each on one thread keeps them
    # from stalling each other at every parallel region when cores are busy
    torch.set_num_threads(args.threads)
    imaging.steady_page_faults()
    # the app never downloads a model: a client's request reads local files only
    os.environ["HF_HUB_OFFLINE"] = "1"
    policy = depth_choice.configure(models, args.allow_any_depth_model)
    for name in policy.models:
        if not depth_sources.hub_model_cached(name):
            log.warning(
                "depth model %s is not in the local Hugging Face cache; clients that pick it "
                "are refused until it is downloaded (hf download %s)", name, name,
            )  # fmt: skip
    try:
        model = load_model(args.weights)
    except (FileNotFoundError, ValueError) as err:
        parser.error(str(err))
    demo = build_demo(model)
    # quiet: Gradio's own start-up lines include advice to set share=True, an option d2f-app
    # does not have; the address is printed here instead
    demo.launch(
        server_name=args.host,
        server_port=args.port,
        share=False,
        quiet=True,
        prevent_thread_lock=True,
        **launch_options(),
    )
    print(f"d2f-app: serving at {demo.local_url} (stop with Ctrl+C)", flush=True)
    demo.block_thread()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

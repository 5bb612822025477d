"""The D2F refocusing web app (Gradio): page layout, event wiring and the ``d2f-app`` CLI.

Start it with ``d2f-app`` or ``python -m app`` (http://127.0.0.1:7860). The logic lives in
:mod:`app.handlers`; rendering and click-to-focus are done by ``d2f_core.pipeline.D2F``.
"""

from __future__ import annotations

import argparse
import inspect
import logging
import os
from typing import Any

import gradio as gr
from gradio.route_utils import FnIndexInferError

from app import imaging
from app import sources as depth_choice
from app.cache import SceneCache
from app.guards import refuse_bad_requests, refuse_unknown_event
from app.handlers import RefocusApp
from app.sessions import delete_session
from app.settings import (
    DEFAULT_F_NUMBER,
    DEPTH_KINDS,
    F_NUMBER_RANGE,
    FOCAL_RANGE_MAX,
    FOCAL_RANGE_STEP,
    FORMATS,
    QUALITIES,
    VIEWS,
)
from app.uploads import UploadGate
from d2f_core import bundled
from d2f_core.depth import sources as depth_sources

log = logging.getLogger(__name__)

SAMPLES_DIR = bundled.assets_dir() / "samples"
#: Events that run the model share one concurrency group of this many parallel calls
#: (all sessions together); on a 2-core CPU more only adds contention.
DEFAULT_CONCURRENCY = 4
#: Gradio drops a session's state this long (seconds) after it was last set; the app
#: closes idle sessions itself, sooner (``D2F_APP_SESSION_IDLE_S``, app/handlers.py).
SESSION_TTL_S = 3600
#: Height in px of the photo and result panels: at 1400x900 the photo, the examples and
#: both sliders fit above the fold.
PANEL_HEIGHT = 360
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


def holding_download(outputs: tuple) -> tuple:
    """A render's outputs and an update of the Download button: disabled when the render
    shows a new picture (its status line is text), until the chained download event hands
    it that picture's file; a click in between would save the previous render."""
    changed = isinstance(outputs[-1], str)
    return (*outputs, gr.update(interactive=False) if changed else gr.skip())


def sample_paths() -> list[str]:
    """The bundled example photos (``assets/samples/``, installed with the package), by name."""
    return [str(p) for p in bundled.sample_photos()]


def load_model(weights: str | os.PathLike | None = None) -> Any:
    """``D2F.from_pretrained`` with an optional weights path (else env ``D2F_WEIGHTS``)."""
    from d2f_core.pipeline import D2F

    if weights is not None:
        return D2F.from_pretrained(weights)
    return D2F.from_pretrained()


def hub_model_input() -> tuple[Any, list]:
    """The hub model control under the depth source, and the events that load with it: the
    operator's models in a list (``--depth-models``), or a text box for any id or folder
    where the operator allows it (``--allow-any-depth-model``, local use only); hidden when
    no hub model is offered."""
    policy = depth_choice.POLICY
    offered = any(v == "transformers" for _, v in depth_choice.choices())
    if policy.models and not policy.any_model:
        box = gr.Dropdown(
            list(policy.models),
            value=policy.models[0],
            label="Hugging Face depth model (the models this server offers)",
            visible=offered,
            elem_id="hub_model",
        )
        return box, [box.input]
    box = gr.Textbox(
        label="Hugging Face depth model: id or folder on this computer (from the local "
        "Hugging Face cache; nothing is downloaded)",
        placeholder=policy.models[0] if policy.models else depth_choice.HUB_PLACEHOLDER,
        visible=offered,
        elem_id="hub_model",
    )
    return box, [box.submit]


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
    # one group for every event that runs the model, so the CPU is not oversubscribed
    heavy = {"concurrency_id": "model", "concurrency_limit": concurrency}
    quiet = {"show_progress": "hidden", "trigger_mode": "always_last"}
    # events that can take over a second at 12 MP show that they are running on the picture
    # they will replace: a spinner over it for an upload or a click (the user waits for
    # them), the running time in its corner for a full render after a slider or an option
    # (no overlay: the drag's previews stay unobstructed). Previews show nothing.
    waited = {"show_progress": "full", "trigger_mode": "always_last"}
    timed = {"show_progress": "minimal", "trigger_mode": "always_last"}
    chained = {"show_progress": "hidden", "api_visibility": "private", "api_name": "auto_download"}

    with gr.Blocks(title="D2F refocus", delete_cache=(600, 3600)) as demo:
        session = gr.State(None, time_to_live=SESSION_TTL_S, delete_callback=delete_session)
        gr.Markdown(INTRO)
        with gr.Row():
            with gr.Column(scale=1):
                photo = gr.Image(
                    label="Photo (click to focus)",
                    type="filepath",
                    sources=["upload", "clipboard"],
                    elem_id="input",
                    height=PANEL_HEIGHT,
                )
                # right under the photo, so that a newcomer sees them without scrolling
                examples = None
                if sample_paths():
                    examples = gr.Examples(
                        sample_paths(), inputs=[photo], label="Examples", elem_id="examples"
                    )
                # 0 = the nearest thing in the photo, 1 = the farthest (disparity = 1 - value)
                focus = gr.Slider(
                    0.0,
                    1.0,
                    value=0.5,
                    step=0.001,
                    label="Focus: near ← → far",
                    elem_id="focus",
                )
                # a click sets it to the clicked subject's extent in depth; 0 = thin lens
                focal_range = gr.Slider(
                    0.0,
                    FOCAL_RANGE_MAX,
                    value=0.0,
                    step=FOCAL_RANGE_STEP,
                    label="Focal range: depth kept sharp around the focus (0 = thin lens)",
                    info="A click sets it to cover the clicked subject",
                    elem_id="focal_range",
                )
                # the f-number of a virtual lens; K in px follows from the photo's long side,
                # and the slider's info line says what it is for this photo
                blur = gr.Slider(
                    *F_NUMBER_RANGE,
                    value=DEFAULT_F_NUMBER,
                    step=0.1,
                    label="Aperture: f-number (smaller = more blur)",
                    info=RefocusApp.blur_note(None, DEFAULT_F_NUMBER),
                    elem_id="blur",
                )
                blur_on = gr.Checkbox(
                    value=True, label="Blur (untick for the photo as it is)", elem_id="blur_on"
                )
                with gr.Accordion("Advanced", open=False):
                    blades = gr.Dropdown(
                        choices=[
                            ("round", 0),
                            ("5 blades", 5),
                            ("6 blades", 6),
                            ("7 blades", 7),
                            ("8 blades", 8),
                            ("9 blades", 9),
                        ],
                        value=0,
                        label="Aperture shape (blades)",
                        elem_id="blades",
                    )
                    rotation = gr.Slider(
                        0.0,
                        180.0,
                        value=0.0,
                        step=1.0,
                        label="Blade rotation (degrees)",
                        elem_id="rotation",
                    )
                    highlight = gr.Checkbox(
                        value=True, label="Highlight boost (bright bokeh balls)", elem_id="hdr"
                    )
                    fusion = gr.Checkbox(
                        value=True,
                        label="Fusion (keep in-focus detail at full resolution)",
                        elem_id="fusion",
                    )
                    quality = gr.Radio(
                        list(QUALITIES),
                        value="balanced",
                        label="Quality / speed (error budget: 45 / 40 / 30 dB)",
                        elem_id="quality",
                    )
                with gr.Accordion("Your own depth map (optional)", open=False):
                    depth = gr.File(
                        label="Depth or disparity image (PNG/TIFF, 8/16-bit) or .npy",
                        elem_id="depth",
                    )
                    depth_kind = gr.Radio(
                        list(DEPTH_KINDS),
                        value=DEPTH_KINDS[0],
                        label="The map holds",
                        elem_id="depth_kind",
                    )
                with gr.Accordion("Depth source", open=False):
                    depth_source = gr.Radio(
                        depth_choice.choices(),
                        value=depth_choice.AUTO,
                        label="Depth from",
                        info=depth_choice.NETWORK_NOTE,
                        elem_id="depth_source",
                    )
                    hub_model, hub_events = hub_model_input()
            with gr.Column(scale=1):
                view = gr.Radio(list(VIEWS), value=VIEWS[0], label="View", elem_id="view")
                result = gr.Image(
                    label="Result",
                    format="jpeg",
                    interactive=False,
                    elem_id="result",
                    height=PANEL_HEIGHT,
                    buttons=["fullscreen"],
                )
                compare = gr.ImageSlider(
                    label="Before / after",
                    format="jpeg",
                    interactive=False,
                    visible=False,
                    elem_id="compare",
                    max_height=PANEL_HEIGHT,
                )
                legend = gr.HTML(visible=False, elem_id="legend", label="Legend")
                info = gr.Textbox(label="Status", interactive=False, elem_id="info")
                with gr.Row():
                    fmt = gr.Radio(
                        list(FORMATS), value="JPEG", label="Download format", elem_id="format"
                    )
                    # nothing to save before the first full render
                    download = gr.DownloadButton("Download", elem_id="download", interactive=False)
                # which photo the page shows (its session's token, set by the load): every
                # render event sends it, and one sent for the photo before is dropped
                photo_id = gr.Textbox("", visible="hidden", interactive=False, elem_id="photo_id")

        options = [blades, rotation, highlight, fusion, view, quality]
        shown = [result, compare, legend, info]

        def load_ui(*values):
            # a large photo's first look, then its full render (an API client gets the last)
            first = True
            for outputs in logic.load_steps(*values):
                # set with the first picture (with the session and the focus): a Lens Blur
                # file's embedded original in the photo panel, the thin lens the photo is
                # rendered with, and the photo's id; later pictures leave them
                page = (gr.skip(),) * 3
                if first:
                    cleared = outputs[0] is None
                    thin_lens = gr.skip() if cleared else 0.0
                    page = (logic.photo_panel(outputs[0]), thin_lens, logic.photo_id(outputs[0]))
                first = False
                yield (*holding_download(outputs), *page)

        def render_full_ui(*values):
            return holding_download(logic.render_full(*values))

        # the handlers' parameters name the API's inputs, and Gradio passes the request
        # (the tab's session hash, for load) by its annotation
        load_signature = inspect.signature(logic.load_steps)
        load_signature = load_signature.replace(
            parameters=[p for p in load_signature.parameters.values() if p.name != "first_look"]
        )
        for ui, signature in (
            (load_ui, load_signature),
            (render_full_ui, inspect.signature(logic.render_full)),
        ):
            ui.__signature__ = signature
            ui.__annotations__ = {"request": gr.Request}

        load_io = {
            "fn": load_ui,
            "inputs": [
                photo,
                depth,
                depth_kind,
                session,
                focus,
                blur,
                *options,
                depth_source,
                hub_model,
                blur_on,
            ],  # fmt: skip
            # the photo, the focal range and the photo's id last: the API's outputs before
            # them keep their places
            "outputs": [session, focus, *shown, download, photo, focal_range, photo_id],
            # raw upload payloads: decoding errors are reported by the app, not by Gradio
            "preprocess": False,
            "show_progress_on": [result, compare],
            **heavy,
            **waited,
        }
        # .upload, not .change: an upload fires .change twice in Gradio 6, and the two runs
        # then race on the same output file; and the load sets the photo panel (a Lens Blur
        # file's original), which fires .change but not .upload
        # a new depth source re-prepares this photo only (.input: the user's choice, not the
        # choices offered again for a new photo)
        loading = gr.on([photo.upload, photo.clear, depth.change, depth_kind.change,
                         depth_source.input, *hub_events], api_name="load",
                        **load_io)  # fmt: skip
        loading.success(logic.download, [session, fmt], [download], **chained)

        # the aperture slider's info line: the blur in px that it gives the photo
        def blur_note_ui(state, f_number, on):
            # the info line only: an update without a value sets no value (and fires no
            # .change or .release of the slider)
            return gr.update(info=logic.blur_note(state, f_number, on))

        note_io = {
            "fn": blur_note_ui,
            "inputs": [session, blur, blur_on],
            "outputs": [blur],
            "show_progress": "hidden",
            "api_visibility": "private",
            "queue": False,
        }
        loading.success(**note_io)
        # a failed upload: the photo panel shows the loaded photo again (or nothing), and the
        # status line keeps the error after the toast is gone
        loading.failure(
            logic.after_failed_load,
            [session, photo],
            [photo, *shown, download],
            preprocess=False,
            show_progress="hidden",
            api_visibility="private",
        )
        # the photo's own depth is offered only when the photo has some (a sample too)
        offer_io = {
            "fn": lambda payload: depth_choice.offer(payload, files),
            "inputs": [photo],
            "outputs": [depth_source],
            "preprocess": False,
            "api_visibility": "private",
            "show_progress": "hidden",
        }
        photo.upload(**offer_io)
        if examples is not None:
            examples.load_input_event.then(**offer_io)
            example_load = examples.load_input_event.then(api_visibility="private", **load_io)
            example_load.success(logic.download, [session, fmt], [download], **chained)
            example_load.success(**note_io)

        # blur_on, the focal range and the photo's id last: the API's inputs before them keep
        # their places (an API client may leave the id out)
        render_inputs = [session, focus, blur, *options, blur_on, focal_range, photo_id]
        # renders run side by side and reach the page in their own order: after each one,
        # the page's picture is brought in line with its controls (RenderEvents.settle: a
        # full render sent again, or, rarely, rendered)
        settle_io = {
            "fn": logic.settle,
            "inputs": [*render_inputs, info],
            "outputs": [*shown, download],
            "show_progress": "hidden",
            "api_visibility": "private",
            **heavy,
        }

        # after a render, Download is enabled only when the page shows that render
        download_io = {"fn": logic.download, "inputs": [session, fmt, info], "outputs": [download]}

        def settled(event: Any) -> None:
            # the one download of each preview, full render or option: after settle, so that
            # it hands out the file of the picture that stays on the page
            event.then(**settle_io).success(**download_io, **chained)

        # .input only: the user's own moves of a slider, each followed by a release (never
        # .change as well: two concurrent runs break the image). A value set by an event (the
        # load's focus and thin lens, a click's focus and range) is rendered by that event
        # in full: a preview of it would stay on screen with no release to follow.
        for slider in (focus, blur, rotation, focal_range):
            # a preview also disables Download until the full render is there to save
            previewed = slider.input(
                logic.render_preview,
                render_inputs,
                [*shown, download],
                api_name=f"preview_{slider.elem_id}",
                **heavy,
                **quiet,
            )
            settled(previewed)
            released = slider.release(
                render_full_ui,
                render_inputs,
                [*shown, download],
                api_name=f"render_{slider.elem_id}",
                show_progress_on=[result, compare],
                **heavy,
                **timed,
            )
            settled(released)
        optioned = gr.on(
            [blades.change, highlight.change, fusion.change, quality.change, blur_on.change],
            render_full_ui,
            render_inputs,
            [*shown, download],
            api_name="render",
            show_progress_on=[result, compare],
            **heavy,
            **timed,
        )
        settled(optioned)
        gr.on([blur.change, blur_on.change], trigger_mode="always_last", **note_io)

        # Gradio finds the event data by the annotation of a named positional parameter and
        # puts it at that parameter's place; the inputs follow it in order
        def on_select(evt: gr.SelectData, state, *values):
            # a large photo refocused at the render pass's size first, then in full
            for outputs in logic.click_steps(state, evt.index, *values):
                yield holding_download(outputs)

        clicked = photo.select(
            on_select,
            [session, blur, *options, blur_on, photo_id],
            [focus, focal_range, *shown, download],
            api_visibility="private",
            show_progress_on=[result, compare],
            **heavy,
            **waited,
        )

        # A click while a slider's number box has the keyboard focus also sends that
        # slider's release (the box loses focus) with the old focus; that full render can
        # start after the click's, win, and leave the click's new focus to a preview with
        # Download disabled. A full render of the values now on the page follows the
        # click: nothing to do when the click's render stands (same params), nor without a
        # photo (the click said so already).
        def refresh_ui(state, *values):
            if state is None:
                return (*(gr.skip(),) * len(shown), gr.skip())
            return render_full_ui(state, *values)

        clicked.success(
            refresh_ui,
            render_inputs,
            [*shown, download],
            api_visibility="private",
            **heavy,
            **quiet,
        ).success(logic.download, [session, fmt], [download], **chained)
        view.change(
            logic.show_view,
            [session, view],
            [result, compare, legend],
            api_name="view",
            show_progress="hidden",
        )
        fmt.change(
            logic.download, [session, fmt], [download], api_name="download", show_progress="hidden"
        )

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
    keeps (:data:`STATE_SESSIONS`) and the server's answer to a request for an event that
    does not exist (:func:`refuse_unknown_event`)."""
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

"""The refocusing page's panels: the photo, the lens's controls, the brushes, the depth, and
the result. Each builds its components in the current ``gr.Blocks`` and returns them by name;
:func:`app.main.build_demo` lays them out and :mod:`app.wiring` connects them.
"""

from __future__ import annotations

from types import SimpleNamespace
from typing import Any

import gradio as gr

from app import sources as depth_choice
from app.handlers import RefocusApp
from app.painting import BLUR_COLOUR, BRUSH_OPACITY, SHARP_COLOUR, bound_canvas
from app.settings import (
    BOOST_MAX,
    DEFAULT_F_NUMBER,
    DEPTH_KINDS,
    F_NUMBER_RANGE,
    FOCAL_RANGE_MAX,
    FOCAL_RANGE_STEP,
    FORMATS,
    LOUPE_SIZE,
    QUALITIES,
    VIEWS,
)
from d2f_core import bundled

SAMPLES_DIR = bundled.assets_dir() / "samples"
#: Height in px of the photo and result panels: at 1400x900 the photo, the examples and
#: both sliders fit above the fold.
PANEL_HEIGHT = 360


def integer_choices(dropdown: gr.Dropdown) -> gr.Dropdown:
    """``dropdown`` (of whole-number choices) advertised to API clients as the integers it
    takes (Gradio says "string" for any choice), and taking a number written as text ("6")
    too; returns it. (An instance's methods are replaced: a subclass of a Gradio component
    makes Gradio write a stub file beside this module.)"""
    preprocess = dropdown.preprocess

    def api_info() -> dict[str, Any]:
        return {"type": "integer", "enum": [value for _, value in dropdown.choices]}

    def as_number(payload: Any) -> Any:
        if isinstance(payload, str):
            try:
                number = float(payload.strip())
            except ValueError:
                pass  # refused by the choices' check, naming the value
            else:
                payload = int(number) if number.is_integer() else payload
        return preprocess(payload)

    dropdown.api_info = api_info
    dropdown.preprocess = as_number
    return dropdown


def sample_paths() -> list[str]:
    """The bundled example photos (``assets/samples/``, installed with the package), by name."""
    return [str(p) for p in bundled.sample_photos()]


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


def input_panel() -> SimpleNamespace:
    """The photo (click to focus) and the examples under it."""
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
        examples = gr.Examples(sample_paths(), inputs=[photo], label="Examples", elem_id="examples")
    return SimpleNamespace(photo=photo, examples=examples)


def lens_controls() -> SimpleNamespace:
    """Focus, focal range, aperture, the blur switch, and the lens's "Advanced" options."""
    # 0 = the nearest thing in the photo, 1 = the farthest (disparity = 1 - value)
    focus = gr.Slider(0.0, 1.0, value=0.5, step=0.001, label="Focus: near ← → far", elem_id="focus")
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
    # the f-number of a virtual lens; K in px follows from the photo's long side, and the
    # slider's info line says what it is for this photo
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
    # Lightroom's "Boost": how bright the discs of clipped lights come out
    highlight = gr.Slider(
        0.0,
        BOOST_MAX,
        value=1.0,
        step=0.05,
        label="Boost: bright bokeh (0 = none, 1 = as bright as a real lens makes them)",
        elem_id="hdr",
    )
    with gr.Accordion("Advanced", open=False):
        blades = integer_choices(
            gr.Dropdown(
                choices=[("round", 0), *((f"{n} blades", n) for n in range(5, 10))],
                value=0,
                label="Aperture shape (blades)",
                elem_id="blades",
            )
        )
        rotation = gr.Slider(
            0.0, 180.0, value=0.0, step=1.0, label="Blade rotation (degrees)", elem_id="rotation"
        )
        fusion = gr.Checkbox(
            value=True, label="Fusion (keep in-focus detail at full resolution)", elem_id="fusion"
        )
        quality = gr.Radio(
            list(QUALITIES),
            value="balanced",
            label="Quality / speed (error budget: 45 / 40 / 30 dB)",
            elem_id="quality",
        )
    return SimpleNamespace(
        focus=focus, focal_range=focal_range, blur=blur, blur_on=blur_on, blades=blades,
        rotation=rotation, highlight=highlight, fusion=fusion, quality=quality,
    )  # fmt: skip


def brush_panel() -> SimpleNamespace:
    """The focus and blur brushes (:mod:`app.painting`): the photo as a canvas, green keeps
    sharp, red blurs; applied and cleared by buttons."""
    with gr.Accordion("Brushes: keep sharp / blur (correct the depth)", open=False):
        editor = bound_canvas(
            gr.ImageEditor(
                label="Paint: green keeps sharp, red blurs (then Apply paint)",
                type="numpy",
                image_mode="RGBA",
                sources=[],
                transforms=[],
                layers=False,
                brush=gr.Brush(
                    colors=[(SHARP_COLOUR, BRUSH_OPACITY), (BLUR_COLOUR, BRUSH_OPACITY)],
                    default_color=(SHARP_COLOUR, BRUSH_OPACITY),
                    color_mode="fixed",
                ),
                eraser=gr.Eraser(),
                height=PANEL_HEIGHT + 120,
                elem_id="paint",
            )
        )
        edges = gr.Checkbox(
            value=True,
            label="Strokes follow the photo's edges (auto mask)",
            elem_id="paint_edges",
        )
        with gr.Row():
            apply = gr.Button("Apply paint", variant="primary", elem_id="paint_apply")
            clear = gr.Button("Clear paint", elem_id="paint_clear")
    return SimpleNamespace(editor=editor, edges=edges, apply=apply, clear=clear)


def depth_panels() -> SimpleNamespace:
    """A depth map of one's own, and the depth source."""
    with gr.Accordion("Your own depth map (optional)", open=False):
        depth = gr.File(
            label="Depth or disparity image (PNG/TIFF, 8/16-bit) or .npy", elem_id="depth"
        )
        depth_kind = gr.Radio(
            list(DEPTH_KINDS), value=DEPTH_KINDS[0], label="The map holds", elem_id="depth_kind"
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
    return SimpleNamespace(
        depth=depth, depth_kind=depth_kind, depth_source=depth_source, hub_model=hub_model,
        hub_events=hub_events,
    )  # fmt: skip


def result_panel() -> SimpleNamespace:
    """The view, the result (or before / after), the legend, the status line, the download
    and the page's photo id."""
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
    # the region around a click on the result, at the photo's full resolution
    loupe = gr.Image(
        label="100 % view: click the result",
        format="png",
        interactive=False,
        elem_id="loupe",
        height=LOUPE_SIZE[1],
        buttons=["fullscreen"],
    )
    # the picture in a photographer's words; the details (sizes, times, the command that makes
    # the same file) wait behind "Advanced", closed
    summary = gr.Markdown("", elem_id="summary")
    with gr.Accordion("Advanced: sizes, times and the d2f command", open=False, elem_id="details"):
        info = gr.Textbox(show_label=False, interactive=False, elem_id="info")
    with gr.Row():
        fmt = gr.Radio(list(FORMATS), value="JPEG", label="Download format", elem_id="format")
        # nothing to save before the first full render
        download = gr.DownloadButton("Download", elem_id="download", interactive=False)
    # which photo the page shows (its session's token, set by the load): every render event
    # sends it, and one sent for the photo before is dropped
    photo_id = gr.Textbox("", visible="hidden", interactive=False, elem_id="photo_id")
    return SimpleNamespace(
        view=view, result=result, compare=compare, legend=legend, loupe=loupe, summary=summary,
        info=info, fmt=fmt,
        download=download, photo_id=photo_id,
    )  # fmt: skip

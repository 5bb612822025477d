"""The refocusing page's events: what each control sets off (:class:`Wiring`), with the
options they share.
"""

from __future__ import annotations

import inspect
from types import SimpleNamespace
from typing import Any

import gradio as gr

from app import sources as depth_choice
from app.handlers import RefocusApp
from app.summary import summary_line


def holding_download(outputs: tuple) -> tuple:
    """A render's outputs and an update of the Download button: disabled when the render
    shows a new picture (its status line is text), until the chained download event hands
    it that picture's file; a click in between would save the previous render."""
    changed = isinstance(outputs[-1], str)
    return (*outputs, gr.update(interactive=False) if changed else gr.skip())


class Wiring:
    """The page's events: what each control sets off, with the options they share.

    Every event that runs the model is in one concurrency group, so the CPU is not
    oversubscribed. Events that can take over a second at 12 MP show that they are running
    on the picture they will replace: a spinner over it for an upload, a click or the paint
    (the user waits for them), the running time in its corner for a full render after a
    slider or an option (no overlay: the drag's previews stay unobstructed). Previews show
    nothing.
    """

    def __init__(self, page: SimpleNamespace, logic: RefocusApp, concurrency: int, files) -> None:
        self.page, self.logic, self.files = page, logic, files
        self.heavy = {"concurrency_id": "model", "concurrency_limit": concurrency}
        self.quiet = {"show_progress": "hidden", "trigger_mode": "always_last"}
        self.waited = {"show_progress": "full", "trigger_mode": "always_last"}
        self.timed = {"show_progress": "minimal", "trigger_mode": "always_last"}
        # Events chained after a render run once per render: a trigger while the previous
        # run of the same chained event is pending must queue one more run (Gradio's default
        # for .then and .success, "once", drops it: two renders in quick succession, the first
        # one's download still writing its file, left Download disabled under the second)
        self.after = {"trigger_mode": "always_last"}
        self.chained = {
            "show_progress": "hidden", "api_visibility": "private", "api_name": "auto_download",
            **self.after,
        }  # fmt: skip
        p = page
        self.options = [p.blades, p.rotation, p.highlight, p.fusion, p.view, p.quality]
        self.shown = [p.result, p.compare, p.legend, p.info]
        # blur_on, the focal range and the photo's id last: the API's inputs before them keep
        # their places (an API client may leave the id out)
        self.render_inputs = [
            p.session, p.focus, p.blur, *self.options, p.blur_on, p.focal_range, p.photo_id
        ]  # fmt: skip

    def full_render_ui(self) -> Any:
        """The full render's handler as the page calls it: Download held until the chained
        download event hands it the new picture's file."""
        logic = self.logic

        def render_full_ui(*values):
            return holding_download(logic.render_full(*values))

        render_full_ui.__signature__ = inspect.signature(logic.render_full)
        render_full_ui.__annotations__ = {"request": gr.Request}
        return render_full_ui

    def settled(self, event: Any) -> None:
        """After a preview, full render or option: renders run side by side and reach the
        page in their own order, so the page's picture is brought in line with its controls
        (``RenderEvents.settle``: a full render sent again, or, rarely, rendered), then the
        one download of the picture that stays on the page."""
        p, logic = self.page, self.logic
        event.then(
            logic.settle,
            [*self.render_inputs, p.info],
            [*self.shown, p.download],
            show_progress="hidden",
            api_visibility="private",
            **self.heavy,
            **self.after,
        ).success(
            logic.download, [p.session, p.fmt, p.info], [p.download], **self.chained
        )  # after a render, Download is enabled only when the page shows that render

    def _load_io(self) -> dict[str, Any]:
        """The load event's function, inputs and outputs: a large photo's first look, then
        its full render (an API client gets the last)."""
        p, logic = self.page, self.logic

        def load_ui(*values):
            first = True
            for outputs in logic.load_steps(*values):
                # set with the first picture (with the session and the focus): a Lens Blur
                # file's embedded original in the photo panel, the focal range of the
                # automatic focus (the thin lens otherwise), and the photo's id; later
                # pictures leave them
                extra = (gr.skip(),) * 3
                if first:
                    loaded = outputs[0]
                    extra = (logic.photo_panel(loaded), logic.loaded_range(loaded),
                             logic.photo_id(loaded))  # fmt: skip
                first = False
                yield (*holding_download(outputs), *extra)

        # the handlers' parameters name the API's inputs, and Gradio passes the request
        # (the tab's session hash) by its annotation
        signature = inspect.signature(logic.load_steps)
        load_ui.__signature__ = signature.replace(
            parameters=[v for v in signature.parameters.values() if v.name != "first_look"]
        )
        load_ui.__annotations__ = {"request": gr.Request}
        return {
            "fn": load_ui,
            "inputs": [
                p.photo,
                p.depth,
                p.depth_kind,
                p.session,
                p.focus,
                p.blur,
                *self.options,
                p.depth_source,
                p.hub_model,
                p.blur_on,
            ],  # fmt: skip
            # the photo, the focal range and the photo's id last: the API's outputs before
            # them keep their places
            "outputs": [
                p.session,
                p.focus,
                *self.shown,
                p.download,
                p.photo,
                p.focal_range,
                p.photo_id,
            ],  # fmt: skip
            # raw upload payloads: decoding errors are reported by the app, not by Gradio
            "preprocess": False,
            "show_progress_on": [p.result, p.compare],
            **self.heavy,
            **self.waited,
        }

    def _note_io(self) -> dict[str, Any]:
        """The aperture slider's info line: the blur in px that it gives the photo (an update
        without a value sets no value, and fires no .change or .release of the slider)."""
        p, logic = self.page, self.logic

        def blur_note_ui(state, f_number, on):
            return gr.update(info=logic.blur_note(state, f_number, on))

        return {
            "fn": blur_note_ui,
            "inputs": [p.session, p.blur, p.blur_on],
            "outputs": [p.blur],
            "show_progress": "hidden",
            "api_visibility": "private",
            "queue": False,
        }

    def _after_load(self, event: Any, note_io: dict[str, Any]) -> None:
        """What follows a load that succeeded: the download, the aperture's note and the
        brushes' canvas."""
        p, logic = self.page, self.logic
        event.success(logic.download, [p.session, p.fmt], [p.download], **self.chained)
        event.success(**note_io, **self.after)
        event.success(
            logic.paint_canvas,
            [p.session],
            [p.editor],
            show_progress="hidden",
            api_visibility="private",
            **self.after,
        )

    def loading(self) -> None:
        """An upload, a sample, a depth map or a depth source loads the photo (its first
        look, then its full render), then the download, the aperture's note, the brushes'
        canvas; a failed load shows the loaded photo again."""
        p, logic, files = self.page, self.logic, self.files
        load_io, note_io = self._load_io(), self._note_io()
        # .upload, not .change: an upload fires .change twice in Gradio 6, and the two runs
        # then race on the same output file; and the load sets the photo panel (a Lens Blur
        # file's original), which fires .change but not .upload. A new depth source
        # re-prepares this photo only (.input: the user's choice, not the choices offered
        # again for a new photo)
        loading = gr.on([p.photo.upload, p.photo.clear, p.depth.change, p.depth_kind.change,
                         p.depth_source.input, *p.hub_events], api_name="load",
                        **load_io)  # fmt: skip
        self._after_load(loading, note_io)
        # a failed upload: the photo panel shows the loaded photo again (or nothing), and the
        # status line keeps the error after the toast is gone
        loading.failure(
            logic.after_failed_load,
            [p.session, p.photo],
            [p.photo, *self.shown, p.download],
            preprocess=False,
            show_progress="hidden",
            api_visibility="private",
        )
        # the photo's own depth is offered only when the photo has some (a sample too)
        offer_io = {
            "fn": lambda payload: depth_choice.offer(payload, files),
            "inputs": [p.photo],
            "outputs": [p.depth_source],
            "preprocess": False,
            "api_visibility": "private",
            "show_progress": "hidden",
        }
        p.photo.upload(**offer_io)
        if p.examples is not None:
            p.examples.load_input_event.then(**offer_io, **self.after)
            self._after_load(
                p.examples.load_input_event.then(api_visibility="private", **load_io), note_io
            )
        gr.on([p.blur.change, p.blur_on.change], trigger_mode="always_last", **note_io)

    def renders(self) -> None:
        """Sliders (a preview while dragged, the full render on release) and options."""
        p, logic = self.page, self.logic
        render_full_ui = self.full_render_ui()

        # a value set before a photo is loaded is kept quietly (the upload renders with it);
        # an option or an API call with no photo still says what is missing
        def release_ui(state, *values):
            if state is None:
                return (*(gr.skip(),) * len(self.shown), gr.skip())
            return render_full_ui(state, *values)

        release_ui.__signature__ = render_full_ui.__signature__
        release_ui.__annotations__ = render_full_ui.__annotations__
        # .input only: the user's own moves of a slider, each followed by a release (never
        # .change as well: two concurrent runs break the image). A value set by an event
        # (the load's focus and range, a click's focus and range) is rendered by that event
        # in full: a preview of it would stay on screen with no release to follow.
        for slider in (p.focus, p.blur, p.rotation, p.focal_range, p.highlight):
            # a preview also disables Download until the full render is there to save
            previewed = slider.input(
                logic.render_preview,
                self.render_inputs,
                [*self.shown, p.download],
                api_name=f"preview_{slider.elem_id}",
                **self.heavy,
                **self.quiet,
            )
            self.settled(previewed)
            released = slider.release(
                release_ui,
                self.render_inputs,
                [*self.shown, p.download],
                api_name=f"render_{slider.elem_id}",
                show_progress_on=[p.result, p.compare],
                **self.heavy,
                **self.timed,
            )
            self.settled(released)
        optioned = gr.on(
            [
                p.blades.change,
                p.fusion.change,
                p.quality.change,
                p.blur_on.change,
            ],  # fmt: skip
            render_full_ui,
            self.render_inputs,
            [*self.shown, p.download],
            api_name="render",
            show_progress_on=[p.result, p.compare],
            **self.heavy,
            **self.timed,
        )
        self.settled(optioned)

    def clicks(self) -> None:
        """A click on the photo focuses there, with the clicked subject's range."""
        p, logic = self.page, self.logic
        render_full_ui = self.full_render_ui()

        # Gradio finds the event data by the annotation of a named positional parameter and
        # puts it at that parameter's place; the inputs follow it in order
        def on_select(evt: gr.SelectData, state, *values):
            # a large photo refocused at the render pass's size first, then in full
            for outputs in logic.click_steps(state, evt.index, *values):
                yield holding_download(outputs)

        clicked = p.photo.select(
            on_select,
            [p.session, p.blur, *self.options, p.blur_on, p.photo_id],
            [p.focus, p.focal_range, *self.shown, p.download],
            api_visibility="private",
            show_progress_on=[p.result, p.compare],
            **self.heavy,
            **self.waited,
        )

        # A click while a slider's number box has the keyboard focus also sends that
        # slider's release (the box loses focus) with the old focus; that full render can
        # start after the click's, win, and leave the click's new focus to a preview with
        # Download disabled. A full render of the values now on the page follows the
        # click: nothing to do when the click's render stands (same params), nor without a
        # photo (the click said so already).
        def refresh_ui(state, *values):
            if state is None:
                return (*(gr.skip(),) * len(self.shown), gr.skip())
            return render_full_ui(state, *values)

        clicked.success(
            refresh_ui,
            self.render_inputs,
            [*self.shown, p.download],
            api_visibility="private",
            **self.heavy,
            **self.quiet,
        ).success(logic.download, [p.session, p.fmt], [p.download], **self.chained)

    def paint(self) -> None:
        """The brushes: Apply renders with the paint, Clear without it (and empties the
        canvas back to the photo)."""
        p, logic = self.page, self.logic

        def apply_ui(state, editor, edges, *values):
            return holding_download(logic.apply_paint(state, editor, edges, *values))

        def clear_ui(state, *values):
            return (logic.paint_canvas(state), *holding_download(logic.clear_paint(state, *values)))

        for event in (
            p.apply.click(
                apply_ui,
                [p.session, p.editor, p.edges, *self.render_inputs[1:]],
                [*self.shown, p.download],
                api_name="paint",
                show_progress_on=[p.result, p.compare],
                **self.heavy,
                **self.waited,
            ),
            p.clear.click(
                clear_ui,
                self.render_inputs,
                [p.editor, *self.shown, p.download],
                api_name="clear_paint",
                show_progress_on=[p.result, p.compare],
                **self.heavy,
                **self.waited,
            ),
        ):
            event.success(logic.download, [p.session, p.fmt], [p.download], **self.chained)

    def loupe(self) -> None:
        """A click on the result shows that spot at 100 % in the loupe; every new picture of
        the result renders the loupe's region again for the page's values."""
        p, logic = self.page, self.logic

        def on_result_select(evt: gr.SelectData, state, *values):
            return logic.loupe(state, evt.index, *values)

        p.result.select(
            on_result_select,
            self.render_inputs,
            [p.loupe],
            api_visibility="private",
            **self.heavy,
            **self.quiet,
        )
        p.result.change(
            logic.refresh_loupe,
            self.render_inputs,
            [p.loupe],
            api_visibility="private",
            **self.heavy,
            **self.quiet,
        )

    def views(self) -> None:
        """The view and the download format: no render; the summary line follows the
        status line."""
        p, logic = self.page, self.logic
        p.info.change(
            summary_line,
            [p.session, p.info],
            [p.summary],
            show_progress="hidden",
            api_visibility="private",
            queue=False,
        )
        p.view.change(
            logic.show_view,
            [p.session, p.view],
            [p.result, p.compare, p.legend],
            api_name="view",
            show_progress="hidden",
        )
        p.fmt.change(
            logic.download,
            [p.session, p.fmt],
            [p.download],
            api_name="download",
            show_progress="hidden",
        )

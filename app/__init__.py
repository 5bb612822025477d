"""Gradio web app for D2F single-image bokeh and live refocusing (``d2f-app``)."""

"""The "Depth source" control offers the photo's own depth only when the photo has some: for
an upload and for a bundled sample alike (a sample has none: offering it made the app fall
back to the network)."""

from __future__ import annotations

import pytest

from app import sources
from app.cache import SceneCache
from app.panels import sample_paths


def offered(update: dict) -> set[str]:
    return {value for _, value in update["choices"]}


def test_samples_are_not_offered_their_own_depth():
    assert sample_paths()
    for path in sample_paths():
        assert "embedded" not in offered(sources.offer({"path": path}))
        assert "d2f" in offered(sources.offer({"path": path}))


def test_unknown_photo_keeps_every_choice():
    assert "embedded" in offered(sources.offer(None))


@pytest.fixture(scope="module")
def config(tiny_model):
    from app.main import build_demo

    return build_demo(tiny_model, cache=SceneCache(1 << 20)).get_config_file()


def test_example_load_updates_the_depth_source(config):
    by_elem = {c["props"].get("elem_id"): c["id"] for c in config["components"]}
    deps = config["dependencies"]
    examples = by_elem["examples"]
    # the events that put a sample in the photo panel, and what follows them
    sample_events = {d["id"] for d in deps if any(t[0] == examples for t in d["targets"])}
    assert sample_events
    offers = [d for d in deps if d["outputs"] == [by_elem["depth_source"]]]
    assert any(d["trigger_after"] in sample_events for d in offers), offers
    assert any([by_elem["input"], "upload"] in map(list, d["targets"]) for d in offers)

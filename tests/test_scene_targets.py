"""The scene model behind stage 0's targets, on small constructed scenes with known answers,
and the generated scenes where "the bottom of the frame is near" is wrong."""

from __future__ import annotations

import random

import numpy as np
import pytest

from d2f_core.bench.depth_bench import spearman
from d2f_core.train import depth_train, scene_targets
from d2f_core.train.synth import render_pinhole
from d2f_core.train.synth.standing import STANDING_KINDS, make_standing_scene, subject_mask

SKY, BUILDING, ROAD, POLE, WALL, FLOOR = 3, 2, 7, 94, 1, 4


def _street(h=60, w=80):
    """Sky over a building standing on a road: rows 0-19 sky, 20-39 building, 40-59 road."""
    ade = np.full((h, w), ROAD, np.uint8)
    ade[:20] = SKY
    ade[20:40] = BUILDING
    return ade


def test_ground_plane_is_linear_from_the_horizon():
    plane = scene_targets.ground_plane(11, 4, 0.5)
    assert plane.shape == (11, 4)
    np.testing.assert_allclose(
        plane[:, 0], np.clip((np.arange(11) / 10 - 0.5) / 0.5, 0, 1), atol=1e-6
    )


def test_sky_is_farthest_and_things_stand_on_the_ground():
    ade = _street()
    layout, strength = scene_targets.scene_layout(ade, scene_targets.ramp(60, 80))
    assert strength == 1.0  # sky and road cover two thirds of the frame
    sky, building, road = layout[:20], layout[20:40], layout[40:]
    assert sky.max() == 0.0 and building.min() > 0.0  # the sky is farthest
    # the road gets nearer row by row down to the bottom
    assert (np.diff(road[:, 40]) > 0).all() and road[-1, 40] == pytest.approx(1.0)
    # the building stands where it meets the road: the road's first row, all the way up
    np.testing.assert_allclose(building[:, 40], road[0, 40], atol=1e-6)
    assert building[:, 40].max() < road[5, 40]


def test_a_close_up_keeps_the_old_layout():
    ade = np.full((40, 40), 13, np.uint8)  # a person filling the frame: no scene
    old = scene_targets.ramp(40, 40)
    layout, strength = scene_targets.scene_layout(ade, old)
    assert strength == 0.0
    np.testing.assert_array_equal(layout, old)


def test_ground_inside_a_thing_is_part_of_it():
    """A patch of ground classes that something surrounds (the coffee in a cup seen from
    above, parsed as floor) is no ground: it stands with the thing round it, where that
    meets the ground; ground that reaches the frame's edge is ground."""
    from d2f_core.depth.layout import open_ground

    plate = 143
    ade = np.full((60, 80), FLOOR, np.uint8)  # a table top seen from above, read as floor
    ade[10:40, 20:60] = plate  # a cup on it
    ade[18:32, 30:50] = FLOOR  # the coffee in the cup, read as floor too
    ground = open_ground(ade)
    assert ground[:10].all() and ground[40:].all() and ground[:, :20].all()
    assert not ground[10:40, 20:60].any()
    layout, strength = scene_targets.scene_layout(ade, scene_targets.ramp(60, 80))
    assert strength == 1.0
    # the cup and its coffee stand where the cup meets the table (row 40): one disparity,
    # nearer than the table seen behind the cup
    np.testing.assert_allclose(layout[10:40, 40], layout[40, 40], atol=1e-6)
    assert layout[10:40, 40].min() > layout[5, 40] + 0.5
    # ground touching the frame's edge stays ground, however it is shaped
    edge = ade.copy()
    edge[18:32, 30:60] = FLOOR  # the patch now runs out of the cup... still inside it
    edge[18:32, 59:] = FLOOR  # ...and on to the frame's edge
    assert open_ground(edge)[20, 40]


def test_horizon_row():
    # the ground's top is row 40, the sky's lowest row 19: the horizon cannot be below the
    # sky, so it is there (less a margin)
    assert scene_targets.horizon_row(_street()) == pytest.approx(18.05 / 59 - 0.03, abs=0.01)
    no_sky = _street()
    no_sky[:20] = BUILDING
    assert scene_targets.horizon_row(no_sky) == pytest.approx(40.95 / 59 - 0.03, abs=0.01)
    assert scene_targets.horizon_row(np.full((30, 30), BUILDING, np.uint8)) == 0.0


def test_subject_stands_at_its_ground_contact_and_in_front():
    ade = _street()
    mask = np.zeros((60, 80), np.float32)
    mask[25:50, 30:45] = 1.0  # a person on the road, feet at row 49
    target = scene_targets.scene_target(ade, scene_targets.ramp(60, 80), mask=mask)
    layout, _ = scene_targets.scene_layout(ade, scene_targets.ramp(60, 80))
    layout = (layout - layout.min()) / (layout.max() - layout.min())
    inside = target[30:45, 33:42]
    # the whole subject has one disparity, at least the road's where it stands
    assert np.ptp(inside) < 1e-5
    assert inside.mean() >= layout[49, 37] - 1e-3
    # nearer than the building and road behind its head and beside it
    assert inside.mean() > target[28, 10] and inside.mean() > target[45, 70]
    assert target[:20].max() == target.min()  # the sky is still the farthest


def test_a_post_across_the_frame_comes_in_front():
    """A pole crossing the frame from top to bottom (no silhouette found) is nearer than the
    sky, building and road that it cuts."""
    ade = _street()
    ade[:, 50:56] = POLE
    target = scene_targets.scene_target(ade, scene_targets.ramp(60, 80))
    pole = target[:, 51:55]
    for rows in (slice(0, 20), slice(20, 40), slice(40, 55)):
        assert pole[rows].mean() > target[rows, 60:].mean()
    # a short pole (half the height) is not an occluder
    short = _street()
    short[20:50, 50:56] = POLE
    assert not scene_targets.occluder_alpha(short).any()


def test_taught_mask_is_the_grown_subjects_and_the_sky():
    h, w = 50, 100
    alpha = np.zeros((h, w), np.float32)
    alpha[20:30, 45:55] = 1.0
    ade = np.full((h, w), ROAD, np.uint8)
    ade[:10] = SKY
    taught = scene_targets.taught_mask(alpha, ade, margin=0.02)  # 2 px at 100 px
    assert taught[:10].all() and taught[20:30, 45:55].all()
    assert taught[20:30, 43].all() and not taught[20:30, 42].any()  # grown by 2 px
    assert not taught[40:].any() and taught.mean() < 0.35
    assert not scene_targets.taught_mask(np.zeros((h, w), np.float32), ade)[10:].any()
    assert not scene_targets.taught_mask(alpha * 0.4).any()  # a faint alpha is no subject
    # scene_target stands exactly scene_subjects in front
    subjects = scene_targets.scene_subjects(ade, mask=alpha)
    assert np.array_equal(subjects, alpha)
    layout = scene_targets.ramp(h, w)
    assert np.array_equal(scene_targets.scene_target(ade, layout, 0.4, mask=alpha),
                          scene_targets.scene_target(ade, layout, 0.4, mask=subjects))  # fmt: skip
    assert np.array_equal(scene_targets.scene_target(ade, layout, 0.4, mask=alpha),
                          scene_targets.stand_on_scene(ade, layout, 0.4, subjects))  # fmt: skip


def test_upside_down_target_scores_badly():
    """Against a generated scene's exact disparity, the target built from its class map
    ranks well, and the same target upside down ranks the other way."""
    h, w = 60, 80
    ade = _street(h, w)
    truth = np.zeros((h, w), np.float32)
    truth[20:40] = 0.3
    truth[40:] = np.linspace(0.3, 1.0, 20)[:, None]
    target = scene_targets.scene_target(ade, scene_targets.ramp(h, w))
    assert spearman(target, truth) > 0.8
    assert spearman(target[::-1], truth) < -0.3


def test_silhouette_is_used_only_when_clear_and_compact():
    sal = np.zeros((64, 64), np.float32)
    sal[20:50, 20:40] = 1.0
    alpha = scene_targets.silhouette_alpha(sal)
    assert alpha is not None and alpha[35, 30] == 1.0 and alpha[5, 5] == 0.0
    # a speck far from the subject is dropped (under a tenth of the largest part)
    sal2 = sal.copy()
    sal2[2:4, 60:62] = 1.0
    assert scene_targets.silhouette_alpha(sal2)[3, 61] == 0.0
    assert scene_targets.silhouette_alpha(np.full((64, 64), 0.45, np.float32)) is None  # none
    assert scene_targets.silhouette_alpha(np.ones((64, 64), np.float32)) is None  # everything
    foggy = np.where(sal > 0, 0.6, 0.4).astype(np.float32)  # no clear edge
    assert scene_targets.silhouette_alpha(foggy) is None
    room = np.full((64, 64), WALL, np.uint8)
    room[40:] = FLOOR
    assert scene_targets.silhouette_alpha(sal, room) is None  # in a room: a shelf, a door


@pytest.mark.parametrize("kind", STANDING_KINDS)
def test_standing_scenes_put_the_subject_in_front(kind):
    for seed in range(3):
        scene = make_standing_scene((64, 96), seed=seed, kind=kind, margin=0)
        _, disp = render_pinhole(scene)
        cover = subject_mask(scene)
        mask = cover > 0.99
        assert mask.sum() > 50
        assert disp[mask] == pytest.approx(scene.subject, abs=1e-5)
        assert disp[cover < 0.01].max() < scene.subject  # nothing else is nearer
        if kind == "post":  # it crosses the frame from top to bottom
            assert mask[0].any() and mask[-1].any()
        if kind == "over":  # the bottom rows are far
            assert disp[-1][cover[-1] < 0.01].max() < scene.subject - 0.3
    same = make_standing_scene((32, 32), seed=5, kind=kind)
    again = make_standing_scene((32, 32), seed=5, kind=kind)
    np.testing.assert_array_equal(render_pinhole(same)[1], render_pinhole(again)[1])
    with pytest.raises(ValueError, match="kind"):
        make_standing_scene((32, 32), seed=0, kind="nope")


def add_scene_labels(labels, pattern: str = "*.npz") -> list[str]:
    """Add the scene teachers' maps to the label files matching ``pattern``: the top half of
    the frame sky, the rest road, nothing salient. Returns the photos' keys."""
    keys = []
    for path in sorted(labels.glob(pattern)):
        with np.load(path) as z:
            maps = dict(z)
        ade = np.full((48, 64), ROAD, np.uint8)
        ade[:24] = SKY
        np.savez(path, **maps, ade=ade, sal=np.zeros((48, 64), np.uint8))
        keys.append(path.stem)
    return keys


def test_training_samples_with_scene_labels(tmp_path):
    """Labels holding the scene teachers' maps give scene targets; older labels keep the
    older targets; standing scenes come in among the generated ones."""
    from test_depth import _tiny_datasets

    root, labels = tmp_path / "datasets", tmp_path / "labels"
    _tiny_datasets(root, labels)
    scene_keys = add_scene_labels(labels, "photos__*.npz")
    data = depth_train.RealDepthData(root, labels, size=(48, 64), paste=0.0, synth=0.0,
                                     scene=True, keep_on="background")  # fmt: skip
    rng = random.Random(0)
    photo = next(p for p in data.photos if p.key in scene_keys)
    _, alpha, target, keep, _ = data._photo(photo, rng, (48, 64))
    assert alpha is None  # the subject (none here) is already in the target
    assert not keep[:8].any()  # the keep term leaves the sky to the target
    # the sky beside the (VOC teacher's) subject is farthest, the road's last row nearest
    assert target[:8, :8].max() < 0.05 and target[-1].min() > 0.8
    # "plain": the keep term is on only where a photo shows no subject and no scene; half
    # this frame is sky and half road, a whole scene: off everywhere
    plain = depth_train.RealDepthData(root, labels, size=(48, 64), paste=0.0, synth=0.0,
                                      scene=True, keep_on="plain")  # fmt: skip
    assert not plain._photo(photo, rng, (48, 64))[3].any()
    # a close-up with no subject (no sky, no ground, nothing salient): on everywhere
    path = labels / f"{photo.key}.npz"
    with np.load(path) as z:
        maps = dict(z)
    maps.update(fg=np.zeros_like(maps["fg"]), ade=np.zeros((48, 64), np.uint8))
    np.savez(path, **maps)
    assert (plain._photo(photo, rng, (48, 64))[3] == 1.0).all()
    assert scene_targets.scene_strength(np.full((48, 64), SKY, np.uint8)) == 1.0
    assert scene_targets.scene_strength(np.full((48, 64), WALL, np.uint8)) == 0.0
    standing = depth_train.RealDepthData(root, labels, size=(48, 64), synth=1.0, standing=1.0)
    s = standing.sample(rng)
    assert not s.relative and s.target.max() >= 0.75  # a standing scene's near subject

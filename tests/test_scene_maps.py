"""The defocus network's scene head (subjects, sky) and what inference does with it:
:func:`d2f_core.depth.scene.stand_subjects`, the head's loss and targets, a short training
run and the pipeline's use of the maps."""

from __future__ import annotations

import dataclasses
import random

import numpy as np
import pytest
import torch

from d2f_core.bench import depth_bench
from d2f_core.bench.depth_bench import subject_auc
from d2f_core.depth.scene import stand_subjects
from d2f_core.io import load_image
from d2f_core.networks import SCENE_MAPS, DefocusNet, build_defocus_net, count_parameters
from d2f_core.pipeline import D2F
from d2f_core.train import depth_cli, depth_train
from d2f_core.train.depth_losses import scene_map_loss
from d2f_core.train.teachers import read_mask

pytestmark = pytest.mark.usefixtures("one_thread")


def _ramp(h: int = 96, w: int = 128) -> np.ndarray:
    """'The bottom is near': 0.1 at the top row to 0.9 at the bottom."""
    return np.tile(np.linspace(0.1, 0.9, h, dtype=np.float32)[:, None], (1, w))


def _box(h: int = 96, w: int = 128, y0=20, y1=60, x0=50, x1=80) -> np.ndarray:
    m = np.zeros((h, w), np.float32)
    m[y0:y1, x0:x1] = 1.0
    return m


class TestStandSubjects:
    def test_a_subject_level_with_its_scene_comes_in_front(self):
        d, subject = _ramp(), _box()
        above = subject[:60] > 0.5  # the frame down to its feet
        assert subject_auc(d[:60], above) < 0.8  # the map alone: level with the scene
        out = stand_subjects(d, subject, lift=0.1)
        part = out[subject > 0.5]
        # three quarters of it are nearer than all that stands beside and above it (the
        # ring's 90th percentile lifted by 0.1 is above the ring's nearest row)
        assert np.percentile(part, 25) > d[:60].max()
        assert subject_auc(out[:60], above) > 0.99
        # the part is shifted as a whole: its own relief is kept
        np.testing.assert_allclose(np.diff(out[20:60, 60]), np.diff(d[20:60, 60]), atol=1e-6)
        # the ground below it and the rest of the frame are untouched
        outside = _box(y0=0, y1=96, x0=0, x1=128) - _box(y0=17, y1=63, x0=47, x1=83)
        np.testing.assert_array_equal(out[outside > 0.5], d[outside > 0.5])

    def test_the_ground_in_front_does_not_push_it(self):
        """A subject standing low in the frame is lifted above what is beside and behind
        it, not above the nearer ground below its feet."""
        d, subject = _ramp(), _box(y0=40, y1=70)
        out = stand_subjects(d, subject, lift=0.1)
        low = np.percentile(out[subject > 0.5], 25)
        assert low > d[:70].max()  # in front of its surroundings
        assert low < d[85, 60]  # not of the ground in front of its feet (0.85 if it counted)

    def test_a_subject_already_in_front_and_small_parts_are_left_alone(self):
        d, subject = _ramp(), _box()
        d[subject > 0.5] = 1.0
        np.testing.assert_array_equal(stand_subjects(d, subject), d)
        speck = _box(y0=20, y1=22, x0=50, x1=52)  # 4 px of 12,288: under min_area
        np.testing.assert_array_equal(stand_subjects(_ramp(), speck), _ramp())
        np.testing.assert_array_equal(stand_subjects(_ramp(), subject, lift=0.0), _ramp())

    def test_the_shift_is_bounded_by_max_shift(self):
        """A part that needs a large shift moves exactly ``max_shift``, as a whole; one that
        needs less than the bound gets what it needs, as without one."""
        d, subject = _ramp(), _box()
        free = stand_subjects(d, subject, lift=0.1)
        need = float(np.median(free[subject > 0.5] - d[subject > 0.5]))
        assert need > 0.25  # the ring's 90th percentile and the lift, over the part's quartile
        out = stand_subjects(d, subject, lift=0.1, max_shift=0.05)
        np.testing.assert_allclose(out[subject > 0.5] - d[subject > 0.5], 0.05, atol=1e-6)
        np.testing.assert_array_equal(out[subject < 0.5], d[subject < 0.5])
        np.testing.assert_array_equal(stand_subjects(d, subject, lift=0.1, max_shift=0.9), free)
        np.testing.assert_array_equal(stand_subjects(d, subject, lift=0.1, max_shift=0.0), d)
        with pytest.raises(ValueError, match="max_shift must be >= 0"):
            stand_subjects(d, subject, max_shift=float("nan"))
        for bad in (-0.1, float("inf"), float("nan")):
            with pytest.raises(ValueError, match="blend must be finite and >= 0"):
                stand_subjects(d, subject, blend=bad)

    def test_blend_follows_the_subject_map(self):
        """``blend`` moves every pixel nearer by its share of the square of the subject map:
        a sure pixel all of it, a hesitant one (0.5) a quarter, the rest none; with no part
        stood (``lift`` 0) nothing else changes, and a move past 1 rescales the whole map."""
        d = _ramp()
        subject = 0.5 * _box(y0=10, y1=30)
        subject[50:70, 50:80] = 1.0
        out = stand_subjects(d, subject, lift=0.0, blend=0.2)
        np.testing.assert_allclose(out[55, 60], d[55, 60] + 0.2, atol=1e-6)
        np.testing.assert_allclose(out[20, 60], d[20, 60] + 0.05, atol=1e-6)
        np.testing.assert_array_equal(out[subject == 0], d[subject == 0])
        # a blend of 0.4 takes the box's lowest row past 1 (1.08): the map is divided by it
        high = stand_subjects(d, subject, lift=0.0, blend=0.4)
        assert high.max() == pytest.approx(1.0)
        np.testing.assert_allclose(high[subject == 0], d[subject == 0] / (d[69, 60] + 0.4))
        # with a part stood too, the blend comes on top of its shift
        both = stand_subjects(d, subject, lift=0.1, max_shift=0.05, blend=0.2)
        np.testing.assert_allclose(both[55, 60], d[55, 60] + 0.25, atol=1e-6)

    def test_blend_needs_no_part_and_no_clarity_and_keeps_the_sky(self):
        """The blend reads the subject map itself: a map under 0.5 everywhere (no part) and
        one under ``min_clarity`` still move by it, and the sky is pulled back with it."""
        d = _ramp()
        faint = 0.4 * _box()  # no pixel reaches 0.5, clarity 0.2
        out = stand_subjects(d, faint, lift=0.1, min_clarity=0.5, blend=0.5)
        np.testing.assert_allclose(out[30, 60], d[30, 60] + 0.5 * 0.16, atol=1e-6)
        np.testing.assert_array_equal(out[faint == 0], d[faint == 0])
        sky = np.zeros_like(d)
        sky[:10] = 1.0
        both = stand_subjects(d, faint, sky, lift=0.0, blend=0.5)
        assert both[:10].max() <= d[10:].min() + 1e-6  # the sky went to the back
        np.testing.assert_allclose(both[30, 60], out[30, 60], atol=1e-6)
        # nothing moved: a map above 1 is clipped, not rescaled
        over = d.copy()
        over[0, 0] = 1.5
        np.testing.assert_array_equal(
            stand_subjects(over, faint, lift=0.1, min_clarity=0.5), np.clip(over, 0, 1)
        )

    def test_a_hesitant_subject_map_stands_nothing(self):
        hesitant = np.where(_box() > 0.5, 0.6, 0.4).astype(np.float32)  # clarity 0.2
        np.testing.assert_array_equal(stand_subjects(_ramp(), hesitant, min_clarity=0.5), _ramp())
        assert not np.array_equal(stand_subjects(_ramp(), hesitant, min_clarity=0.1), _ramp())
        clear = _box()  # clarity 1
        assert not np.array_equal(stand_subjects(_ramp(), clear, min_clarity=0.9), _ramp())

    def test_sky_goes_farthest_and_the_order_is_kept(self):
        d = _ramp()
        d[:30] = 0.6  # a bright sky the network put mid-way
        sky = np.zeros_like(d)
        sky[:30] = 1.0
        out = stand_subjects(d, np.zeros_like(d), sky)
        assert out[:30].max() <= out[30:].min() + 1e-6
        np.testing.assert_array_equal(out[30:], d[30:])
        # a lift past 1 rescales the whole map rather than clipping the subject flat
        high = stand_subjects(_ramp(), _box(), lift=0.3)
        assert high.max() == pytest.approx(1.0) and (np.diff(high[20:60, 60]) > 0).all()
        assert (np.diff(high[:, 10]) > 0).all()  # the scene's own order too

    @pytest.mark.parametrize(
        ("args", "match"),
        [
            ((np.full((8, 8), np.nan), np.zeros((8, 8))), "NaN"),
            ((np.zeros((8, 8)), np.zeros((8, 9))), "subject must be"),
            ((np.zeros((8, 8)), np.zeros((8, 8)), np.zeros(8)), "sky must be"),
            ((np.zeros(8), np.zeros(8)), "disparity must be"),
        ],
    )
    def test_bad_maps_are_named(self, args, match):
        with pytest.raises(ValueError, match=match):
            stand_subjects(*args)


def test_scene_map_loss_counts_known_pixels_only():
    maps = torch.full((2, 2, 4, 4), -1.0)
    assert float(scene_map_loss(torch.zeros(2, 2, 4, 4), maps)) == 0.0  # nothing known
    maps[0, 0] = 1.0
    maps[0, 0, 0, 0] = -1.0
    logits = torch.full((2, 2, 4, 4), 20.0)
    logits[0, 0, 0, 0] = -20.0  # wrong, but unknown there
    assert float(scene_map_loss(logits, maps)) < 1e-6
    logits[0, 0, 1, 1] = -20.0  # wrong on one of the 15 known pixels
    assert float(scene_map_loss(logits, maps)) == pytest.approx(20.0 / 15, rel=1e-4)
    # soft targets: 0.5 is best met by a logit of 0
    soft = torch.full((1, 2, 4, 4), 0.5)
    assert float(scene_map_loss(torch.zeros(1, 2, 4, 4), soft)) == pytest.approx(np.log(2))


def test_scene_head_grows_from_the_plain_network():
    torch.manual_seed(0)
    plain = DefocusNet("lite-ctx").eval()
    torch.nn.init.normal_(plain.context.out.weight, std=0.05)
    net = build_defocus_net("lite-ctx-scene").eval()
    net.load_lite(plain.state_dict())
    x = torch.rand(2, 3, 50, 70)
    with torch.no_grad():
        d, logits = net.forward_scene(x)
        assert torch.equal(d, plain(x)) and torch.equal(net(x), d)
    assert logits.shape == (2, len(SCENE_MAPS), 50, 70)
    assert 0 < count_parameters(net) - count_parameters(plain) < 5_000
    with pytest.raises(ValueError, match="no scene maps"):
        plain.forward_scene(x)
    with pytest.raises(ValueError, match="lite variants"):
        DefocusNet("resnext50", scene_maps=2)


def _scene_labelled(tmp_path):
    """The tiny datasets with scene labels: the top half sky, the rest road."""
    from test_depth import _tiny_datasets
    from test_scene_targets import add_scene_labels

    root, labels = tmp_path / "datasets", tmp_path / "labels"
    _tiny_datasets(root, labels)
    add_scene_labels(labels)
    return root, labels


def test_scene_map_targets_follow_the_depth_targets(tmp_path):
    root, labels = _scene_labelled(tmp_path)
    data = depth_train.RealDepthData(root, labels, size=(48, 64), paste=0.0, synth=0.0,
                                     scene=True, scene_maps=True)  # fmt: skip
    rng = random.Random(0)
    photo = data.masked[0]
    whole = load_image(photo.path)
    img, alpha, layout, _, maps = data._whole(photo, whole, (48, 64))
    assert maps.shape == (2, 48, 64)
    mask = read_mask(photo, (48, 64))  # the human mask the target stands
    assert np.corrcoef(maps[0].ravel(), mask.ravel())[0, 1] > 0.9
    outside = maps[0][mask < 0.01]  # nothing but the 1-px feathered rim
    assert outside.max() < 0.5 and outside.mean() < 0.02
    assert (maps[1][:24] == 1).all() and (maps[1][24:] == 0).all()  # sky above, road below
    # a pasted cut-out is a subject and hides the sky; a flipped sample flips its maps
    cut_rgb, cut_a = np.ones((20, 20, 3), np.float32), np.ones((20, 20), np.float32)
    target = np.zeros((48, 64), np.float32)
    for _ in range(5):
        img2, _, _, maps2 = data._paste(img, target, cut_rgb, cut_a, rng, None, maps)
        pasted = (img2 == 1.0).all(-1) & (img != 1.0).any(-1)
        assert pasted.any() and (maps2[0][pasted] == 1).all() and (maps2[1][pasted] == 0).all()
    # generated scenes carry no scene maps: unknown everywhere in a batch
    synth = depth_train.RealDepthData(root, labels, size=(48, 64), synth=1.0, scene_maps=True)
    assert synth.sample(rng).maps is None
    assert (synth.batch(rng, 2)[4] == -1).all()
    # without scene labels a masked photo's subject is known, its sky is not
    bare = tmp_path / "bare"
    _, bare_labels = bare / "datasets", bare / "labels"
    from test_depth import _tiny_datasets

    _tiny_datasets(bare / "datasets", bare_labels)
    plain = depth_train.RealDepthData(bare / "datasets", bare_labels, size=(48, 64),
                                      paste=0.0, synth=0.0, scene_maps=True)  # fmt: skip
    maps3 = plain._photo(plain.masked[0], rng, (48, 64))[4]
    assert maps3[0].max() > 0.9 and (maps3[1] == -1).all()


def test_scene_variant_trains_exports_and_stands_its_subjects(tmp_path, tiny_checkpoint):
    root, labels = _scene_labelled(tmp_path)
    args = depth_cli.build_parser().parse_args(
        ["--data", str(root), "--labels", str(labels), "--out", str(tmp_path / "run"),
         "--steps", "2", "--batch-size", "2", "--crop", "64", "--save-every", "2",
         "--keep-every", "2", "--workers", "0", "--threads", "1", "--log-every", "1",
         "--variant", "lite-ctx-scene", "--scene-targets", "--synth", "0",
         "--init", str(tiny_checkpoint)]
    )  # fmt: skip
    last = depth_train.train_depth(args)
    log = (tmp_path / "run" / "depth_log.jsonl").read_text().splitlines()
    assert all('"maps"' in line for line in log)
    state = torch.load(last, weights_only=True)["state_dict"]
    init = D2F.from_checkpoint(tiny_checkpoint).defocus_net.state_dict()
    assert {k for k in state if k.startswith("scene_head.")} and set(init) < set(state)
    out = depth_train.export_checkpoint(last, tiny_checkpoint, tmp_path / "d2f.pt")
    model = D2F.from_checkpoint(out)
    assert model.config.defocus == "lite-ctx-scene" and model.config.subject_lift == 0.05
    # the pipeline's map is the network's, with its subjects stood by its own scene maps
    rng = np.random.default_rng(0)
    image = torch.from_numpy(rng.random((1, 3, 64, 96), dtype=np.float32))
    model.config.network_size = 96  # the network runs at the image's own size
    with torch.no_grad():
        # the briefly trained head's subject: the top third of its logits
        first = model.defocus_net.forward_scene(image)[1]
        model.defocus_net.scene_head[2].bias[0] -= float(first[0, 0].quantile(0.67))
        d, logits = model.defocus_net.forward_scene(image)
        got = model.predict_disparity(image, refine=False)
    probs = torch.sigmoid(logits)[0].numpy()
    want = stand_subjects(d[0, 0].numpy(), probs[0], probs[1], lift=0.05)
    assert np.abs(want - d[0, 0].numpy()).max() > 0.01  # it stood some of them
    np.testing.assert_allclose(got[0, 0].numpy(), want, atol=1e-6)
    # config.subject_shift bounds how far a subject moves
    model.config.subject_shift = 0.005
    with torch.no_grad():
        bounded = model.predict_disparity(image, refine=False)[0, 0].numpy()
    small = stand_subjects(d[0, 0].numpy(), probs[0], probs[1], lift=0.05, max_shift=0.005)
    np.testing.assert_allclose(bounded, small, atol=1e-6)
    sky_only = stand_subjects(d[0, 0].numpy(), probs[0], probs[1], lift=0.0)
    assert np.abs(bounded - sky_only).max() <= 0.005 + 1e-6
    model.config.subject_shift = 1.0
    with pytest.raises(ValueError, match="subject_shift must be in"):
        dataclasses.replace(model.config, subject_shift=1.5)
    # --head-only: the scene head learns, the disparity network stays as it started
    head = depth_cli.build_parser().parse_args(
        ["--data", str(root), "--labels", str(labels), "--out", str(tmp_path / "head"),
         "--steps", "2", "--batch-size", "2", "--crop", "64", "--save-every", "2",
         "--keep-every", "2", "--workers", "0", "--threads", "1", "--log-every", "1",
         "--variant", "lite-ctx-scene", "--scene-targets", "--synth", "0", "--head-only",
         "--init", str(out)]
    )  # fmt: skip
    trained = torch.load(depth_train.train_depth(head), weights_only=True)["state_dict"]
    start = model.defocus_net.state_dict()
    assert all(torch.equal(trained[k], v) for k, v in start.items() if "scene_head" not in k)
    assert not torch.equal(trained["scene_head.2.weight"], start["scene_head.2.weight"])
    head.variant, head.out, head.init = "lite-ctx", str(tmp_path / "plain"), str(tiny_checkpoint)
    with pytest.raises(ValueError, match="--head-only needs a '-scene'"):
        depth_train.train_depth(head)
    # nothing to keep as it is without --init; nothing for --keep or --distill to train
    head.variant, head.out, head.init = "lite-ctx-scene", str(tmp_path / "bare"), None
    with pytest.raises(ValueError, match="--head-only needs --init"):
        depth_train.train_depth(head)
    head.init, head.keep = str(out), str(out)
    with pytest.raises(ValueError, match="--keep and --distill"):
        depth_train.train_depth(head)
    head.head_only, head.keep, head.scene_map_weight = False, None, -0.5
    with pytest.raises(ValueError, match="--scene-map-weight must be >= 0"):
        depth_train.train_depth(head)
    assert not (tmp_path / "bare" / "depth_last.pt").exists()
    model.config.subject_lift = 0.0
    with torch.no_grad():
        np.testing.assert_array_equal(model.predict_disparity(image, refine=False), d.numpy())
    # config.subject_blend alone still reads the head: the soft step and the sky, no parts
    model.config.subject_blend = 0.1
    with torch.no_grad():
        blended = model.predict_disparity(image, refine=False)[0, 0].numpy()
    want = stand_subjects(d[0, 0].numpy(), probs[0], probs[1], lift=0.0, blend=0.1)
    np.testing.assert_allclose(blended, want, atol=1e-6)
    assert np.abs(blended - sky_only).max() > 0.01
    # the head's maps and the stand on their own, as `d2f-bench depth --teachers` puts the
    # network's subjects on stage 0's targets: on the network's own map, the pipeline's map
    np.testing.assert_allclose(model.scene_maps(image)[0].numpy(), probs, atol=1e-6)
    np.testing.assert_allclose(model.stand(d[0, 0].numpy(), *probs), blended, atol=1e-6)
    photo = image[0].permute(1, 2, 0).numpy()
    own = depth_bench.subject_blend_predictor(model, lambda im: d[0, 0].numpy())
    np.testing.assert_allclose(own(photo), blended, atol=1e-5)
    flat = depth_bench.subject_blend_predictor(model, lambda im: np.full((32, 48), 0.5))
    assert flat(photo).shape == (32, 48) and flat(photo).max() > 0.5  # the maps are resized
    plain = D2F.from_checkpoint(tiny_checkpoint)
    assert plain.scene_maps(image) is None
    assert depth_bench.subject_blend_predictor(plain, lambda im: d[0, 0].numpy()) is None
    model.config.subject_blend = 0.0
    assert depth_bench.subject_blend_predictor(model, lambda im: d[0, 0].numpy()) is None

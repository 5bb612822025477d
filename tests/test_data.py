"""EBB!-format data set: layouts, splits, identical seeded augmentation."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from d2f_core.train.data import EBBDataset, PairFiles, find_pairs, split_pairs


def write_pairs(
    root: Path,
    count: int = 4,
    size: tuple[int, int] = (64, 64),
    *,
    seed: int = 0,
    layout: str = "folders",
    disparity: bool = True,
    params: bool = True,
    blur: float = 12.0,
) -> Path:
    """Write ``count`` generated pairs in EBB! layout; the target is a blurred far half.

    The image is a 4-px random texture; the disparity is 1 (near) on the left half and 0 on
    the right; the target box-blurs the right half. Returns ``root``.
    """
    rng = np.random.default_rng(seed)
    h, w = size
    root.mkdir(parents=True, exist_ok=True)
    if layout == "folders":
        for sub in ("original", "bokeh", "disparity", "params"):
            (root / sub).mkdir(exist_ok=True)
    for i in range(count):
        cells = rng.integers(0, 256, size=(h // 4 + 1, w // 4 + 1, 3))
        image = cells.repeat(4, 0).repeat(4, 1)[:h, :w].astype(np.uint8)
        target = image.astype(np.float32)
        pad = np.pad(target[:, w // 2 :], ((2, 2), (2, 2), (0, 0)), mode="edge")
        target[:, w // 2 :] = (
            sum(pad[dy : dy + h, dx : dx + w - w // 2] for dy in range(5) for dx in range(5)) / 25.0
        )
        target = target.round().astype(np.uint8)
        disp = np.zeros((h, w), np.uint16)
        disp[:, : w // 2] = 65535
        stem = f"{i:04d}"
        if layout == "folders":
            Image.fromarray(image).save(root / "original" / f"{stem}.png")
            Image.fromarray(target).save(root / "bokeh" / f"{stem}.png")
            if disparity:
                Image.fromarray(disp).save(root / "disparity" / f"{stem}.png")
            if params:
                (root / "params" / f"{stem}.json").write_text(
                    json.dumps({"focus": 1.0, "blur": blur})
                )
        else:
            Image.fromarray(image).save(root / f"{stem}.src.jpg", quality=95)
            Image.fromarray(target).save(root / f"{stem}.tgt.jpg", quality=95)
    return root


class TestFindPairs:
    def test_folder_layout(self, tmp_path):
        root = write_pairs(tmp_path / "d", 3)
        pairs = find_pairs(root)
        assert [p.id for p in pairs] == ["0000", "0001", "0002"]
        assert [p.number for p in pairs] == [0, 1, 2]
        assert all(p.disparity is not None and p.params is not None for p in pairs)

    def test_src_tgt_layout(self, tmp_path):
        root = write_pairs(tmp_path / "d", 2, layout="srctgt")
        pairs = find_pairs(root)
        assert [p.id for p in pairs] == ["0000", "0001"]
        assert pairs[0].input.name == "0000.src.jpg" and pairs[0].target.name == "0000.tgt.jpg"
        assert pairs[0].disparity is None and pairs[0].params is None

    def test_unpaired_files_skipped(self, tmp_path):
        root = write_pairs(tmp_path / "d", 2)
        (root / "bokeh" / "0001.png").unlink()
        assert [p.id for p in find_pairs(root)] == ["0000"]

    def test_errors(self, tmp_path):
        with pytest.raises(FileNotFoundError):
            find_pairs(tmp_path / "missing")
        (tmp_path / "empty").mkdir()
        with pytest.raises(ValueError, match="no image pairs"):
            find_pairs(tmp_path / "empty")


def _fake(numbers):
    return [PairFiles(str(n), n, Path(f"{n}.jpg"), Path(f"{n}.t.jpg")) for n in numbers]


class TestSplits:
    def test_full_ebb_ranges(self):
        pairs = _fake(range(4694))
        val470 = split_pairs(pairs, "val470")
        val294 = split_pairs(pairs, "val294")
        train = split_pairs(pairs, "train")
        assert len(val470) == 470 and val470[0].number == 4224 and val470[-1].number == 4693
        assert len(val294) == 294 and val294[0].number == 4400
        assert len(train) == 4224 and train[-1].number == 4223
        assert len(split_pairs(pairs, "all")) == 4694

    def test_ranges_hold_with_gaps(self):
        pairs = _fake([0, 5, 4223, 4224, 4399, 4400, 4693])
        assert [p.number for p in split_pairs(pairs, "val470")] == [4224, 4399, 4400, 4693]
        assert [p.number for p in split_pairs(pairs, "val294")] == [4400, 4693]
        assert [p.number for p in split_pairs(pairs, "train")] == [0, 5, 4223]

    def test_small_sets_proportional(self):
        pairs = _fake(range(100))
        assert [p.number for p in split_pairs(pairs, "val470")] == list(range(90, 100))
        assert [p.number for p in split_pairs(pairs, "val294")] == list(range(94, 100))
        assert len(split_pairs(pairs, "train")) == 90
        tiny = _fake(range(4))
        assert [p.number for p in split_pairs(tiny, "val470")] == [3]
        assert [p.number for p in split_pairs(tiny, "train")] == [0, 1, 2]

    def test_errors(self):
        with pytest.raises(ValueError, match="split"):
            split_pairs(_fake(range(3)), "test")
        with pytest.raises(ValueError, match="empty"):
            split_pairs(_fake([0]), "train")


class TestDataset:
    def test_item(self, tmp_path):
        ds = EBBDataset(write_pairs(tmp_path / "d", 4, (32, 48)), split="all")
        item = ds[1]
        assert item["id"] == "0001"
        assert item["image"].shape == item["target"].shape == (3, 32, 48)
        assert item["disparity"].shape == (1, 32, 48) and item["has_disparity"]
        assert float(item["disparity"][0, 0, 0]) == 1.0 and float(item["disparity"][0, 0, -1]) == 0
        assert float(item["focus"]) == 1.0 and float(item["blur"]) == 12.0
        assert item["image"].dtype == torch.float32
        assert 0 <= float(item["image"].min()) <= float(item["image"].max()) <= 1

    def test_without_extras(self, tmp_path):
        ds = EBBDataset(write_pairs(tmp_path / "d", 2, layout="srctgt"), split="all")
        item = ds[0]
        assert not item["has_disparity"] and float(item["disparity"].abs().sum()) == 0
        assert torch.isnan(item["focus"]) and torch.isnan(item["blur"])

    def test_crop_and_flip_identical_on_all_maps(self, tmp_path):
        root = write_pairs(tmp_path / "d", 4, (40, 64))
        full = EBBDataset(root, split="all")
        aug = EBBDataset(root, split="all", crop=(16, 24), flip=True, seed=3)
        flips = 0
        for i in range(len(aug)):
            a, f = aug[i], full[i]
            assert a["image"].shape == (3, 16, 24) and a["disparity"].shape == (1, 16, 24)
            # locate the crop in the full image, un-flipping if needed
            found = False
            for flipped in (False, True):
                img = a["image"].flip(-1) if flipped else a["image"]
                tgt = a["target"].flip(-1) if flipped else a["target"]
                dsp = a["disparity"].flip(-1) if flipped else a["disparity"]
                for y in range(40 - 16 + 1):
                    for x in range(64 - 24 + 1):
                        if torch.equal(f["image"][:, y : y + 16, x : x + 24], img):
                            assert torch.equal(f["target"][:, y : y + 16, x : x + 24], tgt)
                            assert torch.equal(f["disparity"][:, y : y + 16, x : x + 24], dsp)
                            found = True
                            flips += flipped
                            break
                    if found:
                        break
                if found:
                    break
            assert found
        assert len(aug) == 4

    def test_seeded(self, tmp_path):
        root = write_pairs(tmp_path / "d", 3, (40, 40))
        a = EBBDataset(root, split="all", crop=16, flip=True, seed=1)
        b = EBBDataset(root, split="all", crop=16, flip=True, seed=1)
        assert all(torch.equal(a[i]["image"], b[i]["image"]) for i in range(3))
        b.set_epoch(1)
        assert not all(torch.equal(a[i]["image"], b[i]["image"]) for i in range(3))

    def test_small_images_enlarged_for_crop(self, tmp_path):
        ds = EBBDataset(write_pairs(tmp_path / "d", 2, (16, 20)), split="all", crop=32)
        item = ds[0]
        assert item["image"].shape == (3, 32, 32)
        assert float(item["blur"]) == pytest.approx(12.0 * 2)

    def test_bad_params(self, tmp_path):
        root = write_pairs(tmp_path / "d", 2)
        (root / "params" / "0000.json").write_text(json.dumps({"focus": 3}))
        with pytest.raises(ValueError, match="0000.json"):
            EBBDataset(root, split="all")[0]

    def test_bad_crop(self, tmp_path):
        with pytest.raises(ValueError, match="crop"):
            EBBDataset(write_pairs(tmp_path / "d", 2), split="all", crop=(0, 4))

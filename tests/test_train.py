"""d2f-train: a tiny seeded end-to-end run on generated EBB-layout pairs."""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np
import pytest
import torch
from test_data import write_pairs

from d2f_core.pipeline import D2F
from d2f_core.train.two_stage import build_parser, main, train

pytestmark = pytest.mark.usefixtures("one_thread")


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    # 4 pairs: 3 train, 1 val470 (small-set rule); target blurs the far half
    return write_pairs(tmp_path_factory.mktemp("ebb"), 4, (64, 64))


def _args(stage, data, out, *extra):
    base = [stage, "--data", str(data), "--out", str(out), "--crop", "64", "--batch-size", "3"]
    base += ["--lr", "1e-3", "--workers", "0", "--log-every", "1", "--device", "cpu"]
    return build_parser().parse_args([*base, *extra])


def _totals(path):
    with path.open() as fh:
        return [float(row["total"]) for row in csv.DictReader(fh)]


@pytest.fixture(scope="module")
def stage1(data, tmp_path_factory):
    out = tmp_path_factory.mktemp("run1")
    return train(_args("stage1", data, out, "--steps", "12", "--val-every", "12"))


def test_stage1_lowers_loss(stage1):
    totals = _totals(stage1.log)
    assert len(totals) == 12
    assert np.mean(totals[-3:]) < 0.8 * np.mean(totals[:3])
    assert stage1.val is not None and np.isfinite(stage1.val[0])
    assert (stage1.checkpoint.parent / "val_stage1.csv").read_text().count("\n") == 2


def test_checkpoint_reloads_to_identical_outputs(stage1):
    loaded = D2F.from_checkpoint(stage1.checkpoint)
    image = np.random.default_rng(0).random((40, 56, 3), dtype=np.float32)
    a = stage1.model.render(stage1.model.prepare(image), 0.7, 10.0)
    b = loaded.render(loaded.prepare(image), 0.7, 10.0)
    np.testing.assert_array_equal(a.bokeh, b.bokeh)
    ckpt = torch.load(stage1.checkpoint, map_location="cpu", weights_only=True)
    assert ckpt["step"] == 12 and ckpt["stage"] == 1 and "optimizer" in ckpt


def test_resume_matches_uninterrupted_run(data, tmp_path):
    full = train(_args("stage1", data, tmp_path / "a", "--steps", "4", "--val-every", "0"))
    half = train(_args("stage1", data, tmp_path / "b", "--steps", "2", "--val-every", "0"))
    resumed = train(
        _args(
            "stage1", data, tmp_path / "b", "--steps", "4", "--val-every", "0",
            "--resume", str(half.checkpoint),
        )
    )  # fmt: skip
    for key, value in full.model.state_dict().items():
        torch.testing.assert_close(resumed.model.state_dict()[key], value, atol=1e-6, rtol=1e-5)
    assert len(_totals(resumed.log)) == 4


def test_stage2_trains_fusion_only(stage1, data, tmp_path):
    result = train(
        _args(
            "stage2", data, tmp_path, "--steps", "6", "--val-every", "0",
            "--init", str(stage1.checkpoint),
        )
    )  # fmt: skip
    before = D2F.from_checkpoint(stage1.checkpoint).state_dict()
    after = result.model.state_dict()
    changed = {k.split(".")[0] for k in before if not torch.equal(before[k], after[k])}
    assert changed == {"fusion_net"}
    with result.log.open() as fh:
        rows = list(csv.DictReader(fh))
    assert "poisson" in rows[0]
    assert float(rows[-1]["poisson"]) < float(rows[0]["poisson"])


def test_resume_wrong_stage(stage1, data, tmp_path):
    with pytest.raises(ValueError, match="stage-1 checkpoint"):
        train(_args("stage2", data, tmp_path, "--steps", "1", "--resume", str(stage1.checkpoint)))


def test_resume_truncated_checkpoint(stage1, data, tmp_path):
    cut = tmp_path / "cut.pt"
    cut.write_bytes(Path(stage1.checkpoint).read_bytes()[:200])
    with pytest.raises(ValueError, match="--resume .* cannot be read: its archive is damaged"):
        train(_args("stage1", data, tmp_path, "--steps", "1", "--resume", str(cut)))
    with pytest.raises(FileNotFoundError, match="--resume checkpoint not found"):
        train(_args("stage1", data, tmp_path, "--steps", "1", "--resume", str(tmp_path / "no.pt")))


def test_cli_errors(tmp_path, data):
    assert main(["stage1", "--data", str(tmp_path / "none"), "--out", str(tmp_path)]) == 2
    args = ["stage1", "--data", str(data), "--out", str(tmp_path), "--batch-size", "8"]
    assert main([*args, "--workers", "0", "--device", "cpu"]) == 2
    with pytest.raises(SystemExit):
        main(["stage3"])


def test_export_applies_config_and_drops_optimizer(stage1, tmp_path):
    ckpt = stage1.checkpoint
    out = tmp_path / "ship" / "model.pt"
    argv = ["export", str(ckpt), str(out), "--set", "network_size=96", "--set", "render_scale=0.5"]
    assert main(argv) == 0
    raw = torch.load(out, map_location="cpu", weights_only=True)
    assert set(raw) == {"config", "state_dict", "version"}
    assert raw["config"]["network_size"] == 96 and raw["config"]["render_scale"] == 0.5
    source = D2F.from_checkpoint(ckpt)
    shipped = D2F.from_checkpoint(out)
    for key, value in source.state_dict().items():
        assert torch.equal(value, shipped.state_dict()[key])
    assert main(["export", str(ckpt), str(out), "--set", "no_such_key=1"]) == 2
    assert main(["export", str(ckpt), str(out), "--set", "render_scale=2"]) == 2


def test_placement_of_a_new_model(data, tmp_path, stage1):
    # a new model renders, trains and is saved with the placement it is given ("paper" for the
    # shipped weights' recipe by default)
    assert stage1.model.config.placement == "paper"
    run = train(
        _args(
            "stage1", data, tmp_path, "--steps", "1", "--val-every", "0", "--placement", "nearest"
        )
    )
    assert run.model.config.placement == "nearest"
    assert D2F.from_checkpoint(run.checkpoint).config.placement == "nearest"


def test_trains_without_tqdm(data, tmp_path, monkeypatch):
    # tqdm is the [train] extra, not a runtime dependency: without it training runs and logs
    import sys

    monkeypatch.setitem(sys.modules, "tqdm", None)  # import tqdm now raises ImportError
    with pytest.raises(ImportError):
        import tqdm  # noqa: F401
    result = train(_args("stage1", data, tmp_path, "--steps", "2", "--val-every", "0"))
    assert len(_totals(result.log)) == 2 and result.checkpoint.is_file()


def test_progress_without_tqdm_iterates_and_ignores_updates(monkeypatch):
    import sys

    from d2f_core.progress import NoBar, logs_above_bar, progress

    monkeypatch.setitem(sys.modules, "tqdm", None)
    bar = progress([3, 1, 2], desc="x")
    assert isinstance(bar, NoBar) and list(bar) == [3, 1, 2]
    bar.update(5)
    bar.set_postfix(loss=1.0)
    bar.set_postfix_str("a")
    bar.close()
    assert list(progress(total=4)) == []
    with logs_above_bar():
        pass

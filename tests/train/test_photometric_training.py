"""The photometric term of the trainer (``CRFDepthModule(photometric_weight=...)``) on a tiny synthetic
drive: camera-view targets by ``crfdepth targets`` from the true poses, neighbours and poses from the
``sequence`` layout; one training step, the weight-0 identity, gradients, data without neighbours."""

from __future__ import annotations

import math
import shutil
import sys
from pathlib import Path
from types import SimpleNamespace

import lightning.pytorch as pl
import pytest
import torch
import yaml

from crfdepth.data import BottomCenterCrop, build_dataset, collate_samples
from crfdepth.data.synthetic import make_sequence
from crfdepth.errors import InputError
from tests.sequence_drive import make_targets, write_drive
from train.data import CRFDataModule, dataset_names
from train.module import CRFDepthModule, depth_loss

#: the shipped structure (configs/kitti_weights.yaml)
SHIPPED = {"mode": "pixel", "variable": "log", "gate": True}


@pytest.fixture(scope="module")
def drive(tmp_path_factory) -> tuple[Path, Path]:
    root = tmp_path_factory.mktemp("photo")
    seq = make_sequence(5, 1, height=176, width=608, movers=1)
    drive = write_drive(root / "raw", seq)
    return root / "raw", make_targets(drive, root / "targets", k=2)


@pytest.fixture(scope="module")
def batch(drive):
    raw, targets = drive
    ds = build_dataset("sequence", raw, targets_root=targets, transform=BottomCenterCrop(128, 448))
    return collate_samples([ds[0], ds[1]])


def step(module: CRFDepthModule, batch) -> tuple[torch.Tensor, dict[str, float]]:
    """``training_step`` with ``self.log`` recorded (no trainer attached)."""
    logged: dict[str, float] = {}
    module.log = lambda name, value, **kw: logged.__setitem__(name, float(torch.as_tensor(value).detach()))  # type: ignore[method-assign]
    return module.training_step(batch, 0), logged


def test_one_training_step_with_the_photometric_term(batch):
    module = CRFDepthModule(crf=SHIPPED, loss="l1", photometric_weight=4.0)
    loss, logged = step(module, batch)
    assert math.isfinite(float(loss))
    # measured at the start: depth L1 0.125 m, photometric 0.033 per frame (weight 4: 0.13, comparable)
    assert 0.01 < logged["train/photometric"] < 0.1, logged
    assert 0.02 < logged["train/depth_loss"] < 0.5, logged
    assert abs(float(loss) - (logged["train/depth_loss"] + 4.0 * logged["train/photometric"])) < 1e-5
    assert abs(logged["train/loss"] - float(loss)) < 1e-6
    loss.backward()
    trained = {n: p for n, p in module.model.named_parameters() if p.requires_grad}
    assert len(trained) >= 10
    no_grad = [n for n, p in trained.items() if p.grad is None or not float(p.grad.abs().sum()) > 0]
    assert no_grad == []


def test_the_photometric_term_alone_reaches_every_depth_weight(batch):
    module = CRFDepthModule(crf=SHIPPED, loss="l1", photometric_weight=1.0)
    _, parts, _ = module._objective(batch)
    parts["photometric"].sum().backward()
    trained = {n: p for n, p in module.model.named_parameters() if p.requires_grad}
    no_grad = [n for n, p in trained.items() if p.grad is None or not float(p.grad.abs().sum()) > 0]
    assert no_grad == []


def test_weight_zero_is_the_depth_loss_alone(batch):
    module = CRFDepthModule(crf=SHIPPED, loss="l1")
    loss, logged = step(module, batch)
    out = module(batch)
    assert "train/photometric" not in logged
    assert abs(float(loss) - float(depth_loss(out.depth, batch.target, "l1").mean())) < 1e-6
    assert abs(float(loss) - logged["train/depth_loss"]) < 1e-7


def test_data_without_neighbours_is_refused():
    module = CRFDepthModule(crf=SHIPPED, photometric_weight=1.0)
    plain = collate_samples([build_dataset("synthetic", count=1, seed=3, height=64, width=192)[0]])
    with pytest.raises(InputError) as info:
        module._objective(plain)
    assert str(info.value) == (
        "photometric_weight: expected data with neighbouring frames and poses (data.layout 'sequence') for "
        "photometric_weight=1, got batches without neighbouring frames; use the sequence layout or set "
        "photometric_weight: 0")
    data = CRFDataModule(layout="synthetic", train_options={"count": 1, "height": 32, "width": 64},
                         val_options={"count": 1, "height": 32, "width": 64, "seed": 1000})
    trainer = pl.Trainer(max_steps=1, logger=False, enable_checkpointing=False, enable_progress_bar=False,
                         enable_model_summary=False, accelerator="cpu", num_sanity_val_steps=0)
    with pytest.raises(InputError, match=r"^photometric_weight: expected data with neighbouring frames and poses "
                                         r"\(data.layout 'sequence'\) for photometric_weight=1, got layout 'synthetic';"):
        trainer.fit(module, datamodule=data)
    for bad in (-1.0, float("nan"), True, "1"):
        with pytest.raises(InputError, match=r"^photometric_weight: expected a number >= 0, got"):
            CRFDepthModule(photometric_weight=bad)


def test_a_source_without_neighbours_beside_a_sequence_layout_gets_no_photometric_term():
    # extra_train sources (e.g. synthetic scenes) mixed into a sequence layout have no neighbours:
    # their batches train on the depth loss alone instead of stopping the run
    module = CRFDepthModule(crf=SHIPPED, loss="l1", photometric_weight=4.0)
    module._trainer = SimpleNamespace(datamodule=SimpleNamespace(layout="sequence"))
    plain = collate_samples([build_dataset("synthetic", count=1, seed=3, height=64, width=192)[0]])
    loss, parts, out = module._objective(plain)
    assert float(parts["photometric"].abs().sum()) == 0.0
    assert abs(float(loss.mean()) - float(depth_loss(out.depth, plain.target, "l1").mean())) < 1e-6
    loss.mean().backward()
    assert any(p.grad is not None and float(p.grad.abs().sum()) > 0 for p in module.model.parameters())


def test_data_module_splits_a_drive_in_blocks(drive):
    raw, targets = drive
    options = {"targets_root": str(targets), "transform": None}
    data = CRFDataModule(layout="sequence", root=str(raw), train_options={**options, "frames": [0, 2]},
                         val_options={**options, "frames": [2, 4]}, flip=1.0, crop=[96, 320])
    data.setup("fit")
    assert len(data.train_set) == 1 and len(data.val_set) == 1  # each block of 3 loses its two ends
    batch = next(iter(data.train_dataloader()))
    assert batch.neighbours.shape == (1, 2, 3, 96, 320) and batch.poses.shape == (1, 2, 4, 4)
    # flipped: the mirrored poses still move 1 m along z per frame
    assert abs(float(batch.poses[0, 0, 2, 3]) - 1.0) < 1e-5 and abs(float(batch.poses[0, 1, 2, 3]) + 1.0) < 1e-5


def test_data_module_holds_out_a_whole_drive_by_name(drive, tmp_path):
    # a folder of several drives (e.g. one per bag, configs/bag_sequence.yaml): val_names_contain
    # holds out whole drives; val_options may differ from train_options (no augmentation)
    raw, targets = drive
    second = "2011_01_01_drive_0002_sync"
    shutil.copytree(raw, tmp_path / "raw")
    shutil.copytree(targets, tmp_path / "targets")
    shutil.copytree(raw / "2011_01_01" / "2011_01_01_drive_0001_sync", tmp_path / "raw" / "2011_01_01" / second)
    shutil.copytree(targets / "2011_01_01_drive_0001_sync", tmp_path / "targets" / second)
    options = {"targets_root": str(tmp_path / "targets"), "transform": None}
    data = CRFDataModule(layout="sequence", root=str(tmp_path / "raw"), val_names_contain="drive_0002",
                         train_options={**options, "beams": [16, 64]}, val_options=options)
    data.setup("fit")
    train, val = dataset_names(data.train_set), dataset_names(data.val_set)
    assert len(train) == 3 and all("drive_0001" in n for n in train)  # 5 frames less the two ends
    assert len(val) == 3 and all("drive_0002" in n for n in val)
    with pytest.raises(InputError, match=r"^val_names_contain=\['drive_0009'\]: the split of the 6 frames"):
        CRFDataModule(layout="sequence", root=str(tmp_path / "raw"), val_names_contain="drive_0009",
                      train_options=options).setup("fit")


def test_the_sequence_config_parses(configs, capsys, monkeypatch):
    from train.__main__ import main

    monkeypatch.setattr(sys, "argv", ["python -m train"])
    with pytest.raises(SystemExit) as exit_info:
        main(["fit", "--config", str(configs / "kitti_sequence.yaml"), "--print_config"])
    assert exit_info.value.code in (0, None)
    printed = yaml.safe_load(capsys.readouterr().out)
    crf = printed["model"]["crf"]  # all five groups (the model's crf is a typed CRFConfig), the config's values in them
    assert list(crf) == ["structure", "potentials", "gate", "solver", "uncertainty"]
    assert (crf["structure"]["mode"], crf["structure"]["variable"], crf["gate"]["enabled"]) == ("pixel", "log", True)
    assert printed["model"]["photometric_weight"] == 0.0 and printed["model"]["loss"] == "l1"
    data = printed["data"]
    assert data["layout"] == "sequence" and data["train_options"]["frames"] == [0, 46]
    assert data["train_options"]["target_input"] == 0.5
    # the raw-scan sources keep drive 0060's sample frames before 52 only: the reported block
    # 52-77 and drive 0001 (the official frames' drive) are never trained on
    extra = data["extra_train"]
    assert [s["layout"] for s in extra] == ["raw", "raw", "object", "object"]  # no synthetic scenes (section 15)
    for source in extra[:2]:
        assert sorted(int(n[-10:]) for n in source["names_contain"]) == list(range(0, 52, 6))
        assert all(n.startswith("drive_0060_sync_") for n in source["names_contain"])
    assert data["val_options"]["frames"] == [52, 77] and data["train_options"]["beams"] == [16, 32, 64]
    assert printed["checkpoint"]["monitor"] == "val/rmse"


def test_the_bag_config_parses_and_splits_whole_bags(configs, capsys, monkeypatch, drive, tmp_path):
    from train.__main__ import main

    monkeypatch.setattr(sys, "argv", ["python -m train"])
    with pytest.raises(SystemExit) as exit_info:
        main(["fit", "--config", str(configs / "bag_sequence.yaml"), "--print_config"])
    assert exit_info.value.code in (0, None)
    data = yaml.safe_load(capsys.readouterr().out)["data"]
    assert data["layout"] == "sequence" and data["root"] == "seq" and data["train_options"]["targets_root"] == "seq"
    assert "beams" not in data["train_options"] and data["val_options"] == {"targets_root": "seq", "offsets": [-1, 1]}
    # the placeholder name holds nothing out: a clear error, not a run without validation
    raw, targets = drive
    for key in ("train_options", "val_options"):
        data[key]["targets_root"] = str(targets)
    module = CRFDataModule(**{**data, "root": str(raw), "num_workers": 0})
    with pytest.raises(InputError, match=r"^val_names_contain=\['name_of_a_held_out_bag'\]: the split of the 3 "
                                         r"frames .* leaves 3 training and 0 validation frames; both need one"):
        module.setup("fit")

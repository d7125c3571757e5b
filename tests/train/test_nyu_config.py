"""configs/nyu.yaml: it parses into the trainer's model and data module, and its data module builds the
Sparse-to-Dense protocol from a small HDF5 tree (nyudepthv2/{train,val}/<scene>/<n>.h5) written here."""

from __future__ import annotations

import sys

import numpy as np
import pytest
import torch
import yaml

from train.data import CRFDataModule, dataset_names

h5py = pytest.importorskip("h5py")


def _tree(root):
    """Three training frames of two scenes and two validation frames, synthetic 640 x 480."""
    rng = np.random.default_rng(0)
    depth = (1.0 + 3.0 * rng.random((480, 640))).astype(np.float32)
    for split, scene, n in [("train", "bedroom_0001", 1), ("train", "bedroom_0001", 6), ("train", "office_0003", 1),
                            ("val", "official", 1), ("val", "official", 2)]:
        folder = root / split / scene
        folder.mkdir(parents=True, exist_ok=True)
        with h5py.File(folder / f"{n:05d}.h5", "w") as f:
            f.create_dataset("rgb", data=rng.integers(0, 256, (3, 480, 640), dtype=np.uint8))
            f.create_dataset("depth", data=depth)
    return root


def test_the_nyu_config_parses(configs, capsys, monkeypatch):
    from train.__main__ import main

    monkeypatch.setattr(sys, "argv", ["python -m train"])
    with pytest.raises(SystemExit) as exit_info:
        main(["fit", "--config", str(configs / "nyu.yaml"), "--print_config"])
    assert exit_info.value.code in (0, None)
    printed = yaml.safe_load(capsys.readouterr().out)
    crf = printed["model"]["crf"]
    assert (crf["structure"]["mode"], crf["structure"]["variable"], crf["gate"]["enabled"]) == ("pixel", "inverse", False)
    assert crf["potentials"]["sigma_p"] == pytest.approx(0.3)
    data = printed["data"]
    assert data["layout"] == "nyu_h5" and data["root"] is None
    assert data["train_options"] == {"split": "train", "samples": 500, "seed": None}
    assert data["val_options"] == {"split": "val", "samples": 500, "seed": 0}


def test_the_nyu_config_builds_the_protocol(configs, tmp_path):
    data = yaml.safe_load((configs / "nyu.yaml").read_text())["data"]
    module = CRFDataModule(**{**data, "root": str(_tree(tmp_path / "nyudepthv2")), "num_workers": 0, "batch_size": 2})
    module.setup("fit")
    assert dataset_names(module.train_set) == ["bedroom_0001_00001", "bedroom_0001_00006", "office_0003_00001"]
    assert dataset_names(module.val_set) == ["official_00001", "official_00002"]
    val = module.val_set[0]
    assert val.size == (228, 304) and int((val.sparse > 0).sum()) == 500
    assert torch.equal(val.sparse, module.val_set[0].sparse)  # validation: the same 500 pixels every time
    torch.manual_seed(0)
    first = module.train_set[0]
    assert first.size == (228, 304) and int((first.sparse > 0).sum()) == 500
    assert not torch.equal(first.sparse > 0, module.train_set[0].sparse > 0)  # training: fresh draws
    batch = next(iter(module.val_dataloader()))
    assert batch.image.shape == (2, 3, 228, 304) and batch.K.shape == (2, 3, 3)


def test_the_nyu_config_takes_an_optimiser_step(configs, tmp_path, monkeypatch):
    """The config's model (pixel grid, inverse depth, no gate) trains on the protocol's 500-sample frames."""
    from train.__main__ import CRFDepthCLI
    from train.module import CRFDepthModule

    monkeypatch.setattr(sys, "argv", ["python -m train"])
    args = ["--config", str(configs / "nyu.yaml"), "--data.root", str(_tree(tmp_path / "nyudepthv2")),
            "--data.num_workers", "0", "--data.batch_size", "1", "--trainer.accelerator", "cpu",
            "--trainer.max_steps", "1", "--trainer.limit_val_batches", "0", "--trainer.num_sanity_val_steps", "0",
            "--trainer.logger", "false", "--trainer.default_root_dir", str(tmp_path), "--trainer.enable_progress_bar",
            "false", "--checkpoint.monitor", "null", "--checkpoint.save_last", "false"]
    cli = CRFDepthCLI(CRFDepthModule, CRFDataModule, args=args, run=False, seed_everything_default=0)
    before = {n: p.detach().clone() for n, p in cli.model.named_parameters() if p.requires_grad}
    cli.trainer.fit(cli.model, cli.datamodule)
    assert cli.trainer.global_step == 1
    after = dict(cli.model.named_parameters())
    moved = [n for n, p in before.items() if not torch.equal(p, after[n].detach())]
    assert moved and all(torch.isfinite(after[n]).all() for n in before)

"""End to end: ``python -m train fit`` on synthetic scenes, on real KITTI frames, with DDP;
checkpoints read back and re-evaluated by ``crfdepth evaluate``; bad input.

Slow (Lightning training in subprocesses; about 2 minutes together on 2 CPU cores) but
part of CI.
"""

from __future__ import annotations

import json
import subprocess
import sys

import pytest
import torch
import yaml

from crfdepth.config import flat_view
from crfdepth.data import build_dataset, collate_samples
from crfdepth.metrics import depth_metrics
from crfdepth.model import CRFDepth
from crfdepth.uncertainty.predictive import DEFAULT_STD_TERMS, STD_TERMS
from train.__main__ import main

# Lightning's CLI calls jsonargparse functions that jsonargparse 4.49 deprecates.
pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning:lightning.pytorch.cli")

WEIGHTS = ("alpha", "beta", "gamma", "delta", "sigma_d", "sigma_n", "sigma_p")
KITTI_VAL_FRAME = "2011_09_26_drive_0001_sync_0000000005_image_02"


def _first_last(scalars, tag):
    values = scalars[tag]
    assert values[0][0] == 0, f"{tag}: expected the validation before training at step 0, got {values}"
    return values[0][1], values[-1][1]


def _best_score(ckpt: dict) -> float:
    (state,) = [v for k, v in ckpt["callbacks"].items() if k.startswith("ModelCheckpoint")]
    return float(state["best_model_score"])


def _learned_weights(ckpt: dict) -> dict[str, float]:
    model = CRFDepth(**ckpt["hyper_parameters"]["crf"])
    model.load_state_dict({k[len("model."):]: v for k, v in ckpt["state_dict"].items() if k.startswith("model.")})
    with torch.no_grad():
        return model.weights()


# ----------------------------------------------------------------------------- synthetic


@pytest.mark.slow
def test_debug_run_on_synthetic_scenes_lowers_validation_loss(tmp_path, configs, train_cli):
    run = train_cli(["fit", "--config", str(configs / "synthetic.yaml"), "--config", str(configs / "debug.yaml")],
                    tmp_path, timeout=300)
    assert run.returncode == 0, run.output[-5000:]
    scalars = run.scalars()
    loss0, loss1 = _first_last(scalars, "val/loss")
    rmse0, rmse1 = _first_last(scalars, "val/rmse")
    print(f"\nsynthetic debug run: {run.seconds:.1f} s; val/loss {loss0:.4f} -> {loss1:.4f} m^2, "
          f"val/rmse {rmse0:.1f} -> {rmse1:.1f} mm")
    # The "under 2 minutes on CPU" acceptance is measured (printed above: ~25 s alone on the
    # 2-core machine), not asserted: shared CI machines make wall-time asserts flaky.
    assert loss1 < loss0 and rmse1 < rmse0
    assert len(scalars["val/loss"]) == 1 + 3  # before training, then after each of the 3 epochs
    assert {f"weights/{n}" for n in WEIGHTS} <= set(scalars)
    names = {p.name for p in run.checkpoints()}
    assert "last.ckpt" in names and any(n.startswith("epoch") for n in names)


@pytest.mark.slow
def test_last_checkpoint_is_the_last_epoch_not_the_best(tmp_path, configs, train_cli):
    # mode "max" makes the first, worst epoch the "best": Lightning's own ModelCheckpoint
    # then leaves last.ckpt at that epoch; the recipe ships last.ckpt as the last epoch.
    run = train_cli(["fit", "--config", str(configs / "synthetic.yaml"), "--config", str(configs / "debug.yaml"),
                     "--checkpoint.mode", "max"], tmp_path, timeout=300)
    assert run.returncode == 0, run.output[-5000:]
    ckpts = {p.name: torch.load(p, map_location="cpu", weights_only=False) for p in run.checkpoints()}
    others = [c["epoch"] for name, c in ckpts.items() if name != "last.ckpt"]
    assert ckpts["last.ckpt"]["epoch"] == 2 and min(others) < 2, (ckpts["last.ckpt"]["epoch"], others)


@pytest.mark.slow
def test_synthetic_config_as_shipped_fits_the_predictive_std(tmp_path, configs, train_cli):
    """synthetic.yaml itself (superpixels, NLL term, loader workers) on smaller scenes: the
    NLL term moves the predictive std's weights (and leaves the posterior's scale alone)."""
    size = "height: 176, width: 608"
    run = train_cli(["fit", "--config", str(configs / "synthetic.yaml"), "--trainer.max_epochs", "2",
                     "--data.train_options", f"{{count: 3, {size}}}",
                     "--data.val_options", f"{{count: 1, seed: 1000, {size}}}"], tmp_path, timeout=300)
    assert run.returncode == 0, run.output[-5000:]
    scalars = run.scalars()
    scale0, scale1 = _first_last(scalars, "weights/std_scale")
    nll = [v for _, v in scalars["train/nll_epoch"]]
    ckpt = torch.load(run.checkpoints()[-1], weights_only=True)
    start = torch.tensor([DEFAULT_STD_TERMS[k] for k in STD_TERMS])
    moved = (ckpt["state_dict"]["model.std_head.weights"] - start).abs()
    print(f"\nsynthetic.yaml, superpixels + NLL ({run.seconds:.1f} s): std weights moved by {moved.tolist()}, "
          f"train NLL per epoch {[round(v, 2) for v in nll]}")
    assert scale0 == scale1 == pytest.approx(1.0) and float(moved.max()) > 0.05
    assert nll[-1] < nll[0]
    assert ckpt["hyper_parameters"]["crf"]["structure"]["mode"] == "superpixel" and ckpt["hyper_parameters"]["nll_weight"] > 0


# ----------------------------------------------------------------------------- real frames


@pytest.fixture(scope="module")
def kitti_run(kitti_root, configs, train_cli, tmp_path_factory):
    """Two epochs on the 13 frames of drive 0060 (pixel mode), validated on drive 0001."""
    log_dir = tmp_path_factory.mktemp("kitti_raw")
    run = train_cli(["fit", "--config", str(configs / "kitti_raw.yaml"),
                     "--data.root", str(kitti_root / "raw"), "--data.num_workers", "0",
                     "--model.crf", "{mode: pixel}", "--model.nll_weight", "0",
                     "--trainer.max_epochs", "2"], log_dir, timeout=400)
    assert run.returncode == 0, run.output[-5000:]
    return run


@pytest.mark.slow
@pytest.mark.kitti
def test_training_on_real_frames_lowers_heldout_rmse(kitti_run):
    scalars = kitti_run.scalars()
    default_rmse = scalars["val/rmse"][0][1]  # step 0: the untrained (default) weights
    best = [p for p in kitti_run.checkpoints() if p.name != "last.ckpt"]
    assert len(best) == 1
    ckpt = torch.load(best[0], weights_only=True)
    learned_rmse = _best_score(ckpt)
    assert learned_rmse == pytest.approx(min(v for _, v in scalars["val/rmse"][1:]))
    initial = flat_view(ckpt["hyper_parameters"]["crf"])
    learned = _learned_weights(ckpt)
    print(f"\nreal frames ({kitti_run.seconds:.1f} s): held-out RMSE on {KITTI_VAL_FRAME}: default weights "
          f"{default_rmse:.1f} mm, learned {learned_rmse:.1f} mm")
    print("weights (initial -> learned): " + ", ".join(f"{n} {initial[n]:.4g} -> {learned[n]:.4g}" for n in WEIGHTS))
    assert learned_rmse < default_rmse - 5.0
    for name in WEIGHTS:
        assert abs(learned[name] - initial[name]) > 1e-3 * initial[name], name


@pytest.mark.slow
@pytest.mark.kitti
def test_checkpoint_loads_with_weights_only(kitti_run):
    for path in kitti_run.checkpoints():
        ckpt = torch.load(path, weights_only=True)
        crf = ckpt["hyper_parameters"]["crf"]
        assert crf == CRFDepth(mode="pixel").config  # complete, plain values
        keys = set(ckpt["state_dict"])
        assert keys == {f"model.{k}" for k in CRFDepth().state_dict()}
        assert ckpt["datamodule_hyper_parameters"]["val_names_contain"] == "drive_0001"

    from crfdepth.checkpoints import load_model

    ckpt = torch.load(kitti_run.checkpoints()[-1], weights_only=True)
    model = load_model(kitti_run.checkpoints()[-1])
    with torch.no_grad():
        assert model.weights() == pytest.approx(_learned_weights(ckpt))


@pytest.mark.slow
@pytest.mark.kitti
def test_evaluate_reproduces_the_validation_rmse(kitti_run, kitti_root, tmp_path, env):
    best = [p for p in kitti_run.checkpoints() if p.name != "last.ckpt"][0]
    logged = _best_score(torch.load(best, weights_only=True))
    # The validation frames are the frames of drive 0001: the first one in name order.
    assert build_dataset("raw", kitti_root / "raw").names[0] == KITTI_VAL_FRAME
    out = tmp_path / "eval"
    proc = subprocess.run([sys.executable, "-m", "crfdepth", "evaluate", "--checkpoint", str(best),
                           "--data", str(kitti_root / "raw"), "--layout", "raw", "--limit", "1",
                           "--out-dir", str(out)], capture_output=True, text=True, env=env, timeout=300)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    per_frame = (out / "per_frame.csv").read_text().splitlines()
    assert len(per_frame) == 2 and per_frame[1].startswith(KITTI_VAL_FRAME + ",")
    summary = json.loads((out / "summary.json").read_text())
    evaluated = summary["metrics"]["rmse"]
    print(f"\nval/rmse logged in training {logged:.4f} mm; crfdepth evaluate {evaluated:.4f} mm")
    assert evaluated == pytest.approx(logged, abs=0.1)


# ----------------------------------------------------------------------------- DDP


@pytest.mark.slow
def test_one_ddp_step_on_two_cpu_processes(tmp_path, configs, train_cli):
    small = "height: 96, width: 320"
    run = train_cli(["fit", "--config", str(configs / "synthetic.yaml"), "--config", str(configs / "debug.yaml"),
                     "--config", str(configs / "ddp.yaml"),
                     "--trainer.accelerator", "cpu", "--trainer.devices", "2",
                     "--trainer.max_epochs", "1", "--trainer.num_sanity_val_steps", "0",
                     # One frame per process for training and for validation. (On the command
                     # line "1" for limit_*_batches parses as the float 1.0: all batches.)
                     "--data.train_options", f"{{count: 2, {small}}}",
                     "--data.val_options", f"{{count: 2, seed: 1000, {small}}}"], tmp_path, timeout=300)
    print(f"\nDDP run, 2 CPU processes: {run.seconds:.1f} s")
    assert run.returncode == 0, run.output[-5000:]
    assert "distributed_backend=gloo" in run.output and "Starting with 2 processes" in run.output
    config = yaml.safe_load((run.version_dir() / "config.yaml").read_text())
    assert config["trainer"]["strategy"] == "ddp" and str(config["trainer"]["devices"]) == "2"
    best = [p for p in run.checkpoints() if p.name != "last.ckpt"]
    assert len(best) == 1 and (best[0].parent / "last.ckpt").exists()
    ckpt = torch.load(best[0], weights_only=True)
    assert ckpt["global_step"] == 1  # one optimizer step, gradients averaged over the 2 processes
    # Each process validated one of the two frames; the logged RMSE is the mean of both.
    model = CRFDepth(**ckpt["hyper_parameters"]["crf"])
    model.load_state_dict({k[len("model."):]: v for k, v in ckpt["state_dict"].items()})
    batch = collate_samples(list(build_dataset("synthetic", count=2, seed=1000, height=96, width=320)))
    with torch.no_grad():
        rmse = depth_metrics(model(batch.image, batch.sparse, batch.K).depth, batch.target)["rmse"]
    assert _best_score(ckpt) == pytest.approx(float(rmse.mean()), abs=0.1)
    assert abs(float(rmse[0]) - float(rmse[1])) > 1.0  # so the check above tells one frame from two


# ----------------------------------------------------------------------------- bad input


@pytest.fixture
def cli(monkeypatch):
    """``train.__main__.main`` run in this process (with ``sys.argv`` cleared)."""
    monkeypatch.setattr(sys, "argv", ["python -m train"])
    return main


def _in_process(args, tmp_path) -> list[str]:
    return [*args, "--trainer.logger.init_args.save_dir", str(tmp_path),
            "--trainer.default_root_dir", str(tmp_path), "--trainer.enable_progress_bar", "false"]


def test_unknown_config_key_is_named(tmp_path, configs, capsys, cli):
    bad = tmp_path / "bad.yaml"
    bad.write_text("model:\n  learning_rate: 0.1\n")
    with pytest.raises(SystemExit) as exit_info:
        cli(_in_process(["fit", "--config", str(configs / "synthetic.yaml"), "--config", str(bad)], tmp_path))
    assert exit_info.value.code != 0
    assert "learning_rate" in capsys.readouterr().err


def test_unknown_command_line_key_is_named(tmp_path, configs, capsys, cli):
    with pytest.raises(SystemExit) as exit_info:
        cli(_in_process(["fit", "--config", str(configs / "synthetic.yaml"), "--data.bogus_option", "1"], tmp_path))
    assert exit_info.value.code != 0
    assert "bogus_option" in capsys.readouterr().err


@pytest.mark.parametrize("sub", ["empty", "missing"])
def test_data_root_without_frames(tmp_path, configs, capsys, cli, sub):
    root = tmp_path / "data"
    if sub == "empty":
        root.mkdir()
    status = cli(_in_process(["fit", "--config", str(configs / "kitti_raw.yaml"), "--config",
                               str(configs / "debug.yaml"), "--data.root", str(root)], tmp_path / "logs"))
    err = capsys.readouterr().err
    assert status == 2
    assert str(root) in err and "'raw'" in err and "Traceback" not in err


@pytest.mark.parametrize("files", [
    ["synthetic.yaml"], ["synthetic.yaml", "debug.yaml"], ["synthetic.yaml", "debug.yaml", "ddp.yaml"],
    ["kitti_raw.yaml"], ["kitti_raw.yaml", "ddp.yaml"], ["kitti_dc.yaml"], ["kitti_weights.yaml"],
])
def test_configs_parse(configs, capsys, cli, files):
    args = ["fit"] + [a for f in files for a in ("--config", str(configs / f))] + ["--print_config"]
    with pytest.raises(SystemExit) as exit_info:
        cli(args)
    assert exit_info.value.code in (0, None)
    printed = yaml.safe_load(capsys.readouterr().out)
    assert printed["checkpoint"]["monitor"] == "val/rmse" and printed["checkpoint"]["mode"] == "min"
    assert printed["model"]["crf"] is not None

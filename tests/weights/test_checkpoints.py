"""Saving and loading CRFDepth checkpoints (crfdepth.weights): the torch file kinds, refusals."""

from __future__ import annotations

import datetime
import os
import pickle
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from crfdepth.checkpoints import load_model, save_model
from crfdepth.errors import InputError
from crfdepth.model import CRFDepth
from crfdepth.weights import MODEL_FORMAT, MODEL_VERSION

F64 = torch.float64


def _frame(h: int = 40, w: int = 56):
    """A small frame: red/blue halves, two planes (8-10 m and 16-20 m), LiDAR on every 4th row."""
    K = torch.tensor([[50.0, 0, w / 2], [0, 50.0, h / 2], [0, 0, 1]])
    v, u = torch.meshgrid(torch.arange(h, dtype=torch.float32), torch.arange(w, dtype=torch.float32),
                          indexing="ij")
    depth = torch.where(u < w // 2, 8.0 + 0.05 * v, 20.0 - 0.1 * v)
    image = torch.full((3, h, w), 0.1)
    image[0, :, : w // 2] = 0.8
    image[2, :, w // 2:] = 0.8
    sparse = torch.zeros(h, w)
    sparse[2::4, 1::2] = depth[2::4, 1::2]
    return image[None], sparse[None, None], K


def _trained(**config) -> CRFDepth:
    """A model whose every parameter differs from its initial value (as after training)."""
    model = CRFDepth(**config)
    with torch.no_grad():
        for i, p in enumerate(model.parameters()):
            p.add_(0.1 * (i + 1))
    return model


def _depth(model: CRFDepth) -> torch.Tensor:
    image, sparse, K = _frame()
    with torch.no_grad():
        return model.to(torch.float32)(image, sparse, K).depth


def _assert_same_parameters(a: CRFDepth, b: CRFDepth) -> None:
    sa, sb = a.state_dict(), b.state_dict()
    assert sa.keys() == sb.keys()
    for k in sa:
        assert sa[k].dtype == sb[k].dtype, k
        torch.testing.assert_close(sa[k], sb[k], rtol=0, atol=0, msg=k)


# --------------------------------------------------------------------------- round trips


@pytest.mark.parametrize("config", [dict(mode="pixel", potentials=("colour", "normal")),
                                    dict(superpixels=300, scale_superpixels=False, refine=False)])
def test_save_then_load_gives_the_same_model(tmp_path, config):
    model = _trained(**config)
    path = save_model(model, tmp_path / "crf.pt")
    assert path == tmp_path / "crf.pt" and sorted(os.listdir(tmp_path)) == ["crf.pt"]  # no temporary left
    raw = torch.load(path, weights_only=True)
    assert raw["format"] == MODEL_FORMAT == "crfdepth" and raw["version"] == MODEL_VERSION == 1
    assert raw["config"] == model.config

    loaded = load_model(path)
    assert isinstance(loaded, CRFDepth) and not loaded.training
    assert loaded.config == model.config and loaded.settings.structure.mode == model.settings.structure.mode
    _assert_same_parameters(loaded, model)
    with torch.no_grad():
        assert loaded.weights() == pytest.approx(model.weights(), rel=1e-6)
        assert loaded.weights()["alpha"] != pytest.approx(CRFDepth().weights()["alpha"])
    torch.testing.assert_close(_depth(loaded), _depth(model), rtol=0, atol=0)


def test_save_keeps_the_dtype_and_replaces_an_existing_file(tmp_path):
    path = tmp_path / "crf.pt"
    save_model(CRFDepth(mode="pixel"), path)
    model = _trained(mode="pixel").double()
    save_model(model, path)  # replaces the first file
    loaded = load_model(path)
    assert loaded.raw_alpha.dtype == F64
    _assert_same_parameters(loaded, model)
    assert sorted(os.listdir(tmp_path)) == ["crf.pt"]


def test_failed_save_leaves_no_file(tmp_path, monkeypatch):
    path = tmp_path / "crf.pt"
    save_model(CRFDepth(), path)
    before = path.read_bytes()

    def broken(obj, f, *args, **kwargs):
        Path(f).write_bytes(b"partial")
        raise OSError("disk full")

    monkeypatch.setattr(torch, "save", broken)
    with pytest.raises(OSError, match="disk full"):
        save_model(_trained(), path)
    assert sorted(os.listdir(tmp_path)) == ["crf.pt"] and path.read_bytes() == before


def test_save_bad_arguments(tmp_path):
    with pytest.raises(InputError, match="model: expected a CRFDepth, got Linear"):
        save_model(torch.nn.Linear(2, 2), tmp_path / "x.pt")
    with pytest.raises(FileNotFoundError, match="no-such-folder"):
        save_model(CRFDepth(), tmp_path / "no-such-folder" / "x.pt")
    with pytest.raises(InputError, match="got a folder"):
        save_model(CRFDepth(), tmp_path)


def _lightning(state: dict, crf: dict | None, **extra) -> dict:
    """A dict shaped like the trainer's Lightning checkpoint (the CRF stored as ``self.model``)."""
    out = {"epoch": 3, "global_step": 120, "pytorch-lightning_version": "2.4.0",
           "state_dict": {f"model.{k}": v for k, v in state.items()} | {"loss.log_scale": torch.zeros(())},
           "optimizer_states": [{"state": {}, "param_groups": [{"lr": 0.01, "params": [0, 1]}]}],
           **extra}
    if crf is not None:
        out["hyper_parameters"] = {"crf": crf, "lr": 0.01}
    return out


def test_lightning_checkpoint_loads_with_its_configuration(tmp_path):
    model = _trained(mode="pixel", potentials=("colour", "distance"), sigma_p=2.0)
    torch.save(_lightning(model.state_dict(), model.config), tmp_path / "last.ckpt")
    loaded = load_model(tmp_path / "last.ckpt", map_location="cpu")
    assert loaded.settings.structure.mode == "pixel" and loaded.settings.potentials.on == ("colour", "distance")
    assert loaded.config == model.config
    _assert_same_parameters(loaded, model)
    torch.testing.assert_close(_depth(loaded), _depth(model), rtol=0, atol=0)
    assert loaded.raw_alpha.device.type == "cpu"


def test_overrides_replace_the_stored_configuration(tmp_path):
    model = _trained(mode="pixel")
    torch.save(_lightning(model.state_dict(), model.config), tmp_path / "last.ckpt")
    loaded = load_model(tmp_path / "last.ckpt", overrides={"mode": "superpixel", "refine": False})
    assert loaded.settings.structure.mode == "superpixel" and loaded.settings.structure.refine is False
    assert loaded.config == CRFDepth(model.config, mode="superpixel", refine=False).config
    _assert_same_parameters(loaded, model)  # the learned weights, in another graph


@pytest.mark.skipif(torch.cuda.is_available(), reason="checks the message on a machine without CUDA")
def test_cuda_map_location_without_cuda(tmp_path):
    save_model(CRFDepth(), tmp_path / "crf.pt")
    with pytest.raises(InputError, match="map_location: CUDA is not available"):
        load_model(tmp_path / "crf.pt", map_location="cuda")


# --------------------------------------------------------------------------- refusals


def _pickle_of_other_objects(path: Path) -> None:
    path.write_bytes(pickle.dumps({"when": datetime.datetime(2020, 1, 1)}, protocol=2))


def _crfdepth_file(**changes):
    def write(path: Path) -> None:
        model = CRFDepth()
        torch.save({"format": MODEL_FORMAT, "version": MODEL_VERSION, "config": model.config,
                    "state_dict": model.state_dict(), **changes}, path)
    return write


BAD = {
    "random bytes": (lambda p: p.write_bytes(bytes(range(256)) * 4),
                     ["is not a torch state dict, crfdepth model file or Lightning checkpoint",
                      "neither a torch.save archive nor a pickle"]),
    "text file": (lambda p: p.write_text("alpha = 0.5\nbeta = 0.5\n"),
                  ["is not a torch state dict", "neither a torch.save archive nor a pickle", "b'alpha = '"]),
    "broken archive": (lambda p: p.write_bytes(b"PK\x03\x04" + bytes(60)),
                       ["is not a torch state dict", "weights_only=True refused it"]),
    "pickle of other objects": (_pickle_of_other_objects,
                                ["is not a torch state dict", "datetime.datetime"]),
    "a tensor": (lambda p: torch.save(torch.ones(3), p), ["does not hold a state dict", "got Tensor"]),
    "empty dict": (lambda p: torch.save({}, p), ["does not hold a state dict", "empty dict"]),
    "wrong keys": (_crfdepth_file(state_dict={"encoder.weight": torch.ones(3)}),
                   ["does not match CRFDepth", "missing keys (11)", "log_confidence",
                    "unexpected keys (1): encoder.weight"]),
    "wrong shape": (_crfdepth_file(state_dict={**CRFDepth().state_dict(), "raw_alpha": torch.ones(2)}),
                    ["does not match CRFDepth", "wrong shapes (1): raw_alpha (2,) instead of ()"]),
    "lightning without hyper_parameters": (
        lambda p: torch.save(_lightning(CRFDepth().state_dict(), None), p),
        ["Lightning checkpoint without the CRF configuration", "hyper_parameters['crf']"]),
    "lightning without crf": (
        lambda p: torch.save({**_lightning(CRFDepth().state_dict(), None), "hyper_parameters": {"lr": 0.1}}, p),
        ["Lightning checkpoint without the CRF configuration", "got hyper_parameters ['lr']"]),
    "lightning of another module": (
        lambda p: torch.save({"state_dict": {"net.conv.weight": torch.ones(2, 2)},
                              "hyper_parameters": {"crf": {}}}, p),
        ["has no 'model.' keys", "net.conv.weight"]),
    "lightning of another configuration": (
        lambda p: torch.save(_lightning({**CRFDepth().state_dict(), "extra": torch.ones(1)}, {}), p),
        ["does not match CRFDepth", "unexpected keys (1): extra"]),
    "unknown configuration key": (
        lambda p: torch.save(_lightning(CRFDepth().state_dict(), {"layers": 3}), p),
        ["Lightning checkpoint's model configuration does not fit CRFDepth", "layers"]),
    "invalid configuration value": (_crfdepth_file(config={"mode": "voxel"}),
                                    ["invalid model configuration", "mode", "voxel"]),
    "future crfdepth file": (_crfdepth_file(version=2), ["crfdepth model file version 2 is not supported"]),
}


@pytest.mark.parametrize("case", list(BAD))
def test_bad_checkpoint_is_refused_naming_the_file(tmp_path, case):
    write, words = BAD[case]
    path = tmp_path / "bad.ckpt"
    write(path)
    with pytest.raises(InputError) as info:
        load_model(path)
    message = str(info.value)
    assert str(path) in message
    for word in words:
        assert word in message, (word, message)


class _CreatesMarker:
    """Unpickling this would run ``open(marker, "w")`` (arbitrary code execution)."""

    def __init__(self, marker: Path):
        self.marker = str(marker)

    def __reduce__(self):
        return (open, (self.marker, "w"))


@pytest.mark.parametrize("protocol", [2, pickle.HIGHEST_PROTOCOL])
@pytest.mark.parametrize("zipped", [False, True])
def test_malicious_pickle_is_not_executed(tmp_path, protocol, zipped):
    marker = tmp_path / "pwned"
    payload = {"hook": _CreatesMarker(marker), "state_dict": {"model.raw_alpha": torch.zeros(())}}
    path = tmp_path / "evil.ckpt"
    if zipped:  # inside the torch.save container, as a real checkpoint would be
        torch.save(payload, path, pickle_protocol=protocol)
    else:
        path.write_bytes(pickle.dumps(payload, protocol=protocol))
    assert not marker.exists()
    with pytest.raises(InputError, match="is not a torch state dict") as info:
        load_model(path)
    assert str(path) in str(info.value)
    assert not marker.exists()  # weights_only refused the file before running anything

    # Control: the file really is harmful to an unsafe loader.
    if zipped:
        torch.load(path, weights_only=False)
    else:
        pickle.loads(path.read_bytes())
    assert marker.exists()


def test_missing_file_and_folder(tmp_path):
    with pytest.raises(FileNotFoundError, match="no such checkpoint file") as info:
        load_model(tmp_path / "none.ckpt")
    assert str(tmp_path / "none.ckpt") in str(info.value)
    with pytest.raises(InputError, match="expected a checkpoint file, got a folder"):
        load_model(tmp_path)


def test_loads_a_lightning_checkpoint_without_lightning(tmp_path):
    """The library reads the trainer's .ckpt where Lightning cannot be imported."""
    model = _trained(mode="pixel")
    torch.save(_lightning(model.state_dict(), model.config), tmp_path / "last.ckpt")
    script = (
        "import sys\n"
        "sys.modules['lightning'] = None\n"  # import lightning -> ImportError
        "sys.modules['pytorch_lightning'] = None\n"
        "from crfdepth import load_model\n"
        f"model = load_model({str(tmp_path / 'last.ckpt')!r})\n"
        "print(model.settings.structure.mode, float(model.alpha))\n"
    )
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120,
                          env={**os.environ, "OMP_NUM_THREADS": "1"})
    assert done.returncode == 0, done.stderr
    mode, alpha = done.stdout.split()
    assert mode == "pixel" and float(alpha) == pytest.approx(float(model.alpha.detach()))


def _model_file(path: Path, state: dict, config: dict | None = None) -> Path:
    """A crfdepth model file holding ``state`` (default configuration unless ``config``)."""
    torch.save({"format": MODEL_FORMAT, "version": MODEL_VERSION,
                "config": CRFDepth().config if config is None else config, "state_dict": state}, path)
    return path


def test_state_dict_with_the_old_refine_prior_buffer_loads(tmp_path):
    model = CRFDepth(refine_prior=0.02)
    state = {k: v for k, v in model.state_dict().items() if k != "log_refine_prior"}
    state["refine_prior"] = torch.tensor(0.02)  # the layout before the prior became learnable
    _model_file(tmp_path / "old.pt", state, model.config)
    loaded = load_model(tmp_path / "old.pt")
    assert float(loaded.refine_prior.detach()) == pytest.approx(0.02, rel=1e-6)
    assert loaded.weights() == pytest.approx(model.weights(), rel=1e-6)


# --------------------------------------------------------------------------- non-finite tensors


@pytest.mark.parametrize("kind", ["crfdepth model file", "Lightning checkpoint"])
@pytest.mark.parametrize("key, value, got", [("raw_alpha", float("nan"), "nan"),
                                             ("log_sigma_d", float("inf"), "inf"),
                                             ("eps", float("-inf"), "-inf")])
def test_non_finite_tensor_is_refused_naming_file_and_parameter(tmp_path, kind, key, value, got):
    state = {**_trained().state_dict(), key: torch.tensor(value)}
    path = tmp_path / "x.ckpt"
    if kind == "crfdepth model file":
        _model_file(path, state)
    else:
        torch.save(_lightning(state, CRFDepth().config), path)
    with pytest.raises(InputError) as info:
        load_model(path)
    assert str(info.value) == f"path: {path}: parameter {key}: expected finite values, got {got}"


def test_non_finite_old_refine_prior_is_named_as_stored(tmp_path):
    state = {k: v for k, v in CRFDepth().state_dict().items() if k != "log_refine_prior"}
    for value, message in ((float("nan"), "expected finite values, got nan"), (0.0, "expected values > 0, got 0.0")):
        _model_file(tmp_path / "old.pt", {**state, "refine_prior": torch.tensor(value)})
        with pytest.raises(InputError) as info:
            load_model(tmp_path / "old.pt")
        assert str(info.value) == f"path: {tmp_path / 'old.pt'}: parameter refine_prior: {message}"


def test_non_finite_entries_of_a_larger_tensor_are_counted(tmp_path):
    from crfdepth.weights.files import read_checkpoint

    _model_file(tmp_path / "x.pt", {"w": torch.tensor([1.0, float("nan"), float("nan"), 2.0]),
                                    "steps": torch.tensor([3])})
    with pytest.raises(InputError, match=r"parameter w: expected finite values, got nan \(2 of 4 values not finite\)"):
        read_checkpoint(tmp_path / "x.pt")


def test_tensors_outside_the_model_are_not_checked(tmp_path):
    """A Lightning checkpoint's other modules (here a NaN loss state) are ignored, as their keys are."""
    model = _trained(mode="pixel")
    ckpt = _lightning(model.state_dict(), model.config)
    ckpt["state_dict"]["loss.log_scale"] = torch.tensor(float("nan"))
    torch.save(ckpt, tmp_path / "last.ckpt")
    _assert_same_parameters(load_model(tmp_path / "last.ckpt"), model)


# --------------------------------------------------------------------------- imports


def test_from_pretrained_builds_the_subclass_it_is_called_on():
    """CRFDepth.from_pretrained of a subclass builds the subclass (the import structure itself is
    tested in tests/test_structure.py)."""
    import crfdepth.model

    class Sub(crfdepth.model.CRFDepth):
        pass

    model = Sub.from_pretrained("paper")
    assert type(model) is Sub and model.config == crfdepth.model.CRFDepth().config

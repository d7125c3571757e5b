"""The library's folder run (crfdepth.runs.folder.complete_folder) called directly with typed options: the same
files as ``crfdepth complete --input-dir``, its report through the caller's callback, bad frames refused or
skipped (crfdepth.runs.skip_bad)."""

from __future__ import annotations

import functools

import pytest

from crfdepth.checkpoints import load_pretrained
from crfdepth.errors import InputError
from crfdepth.runs.folder import FolderResult, FolderRun, complete_folder
from crfdepth.runs.resume import RUN_RECORD, run_record
from crfdepth.runs.skip_bad import skipped_frames
from tests.cli.frames import FAST, files, png, run, same_pngs, write_folder


def _model(quiet: bool):
    return load_pretrained("kitti", potentials=["colour"]).eval()


def test_complete_folder_writes_what_the_command_writes_and_reports(tmp_path):
    data = write_folder(tmp_path / "val_selection_cropped", 2)
    assert run(["complete", "--input-dir", data, "--out-dir", tmp_path / "cli", *FAST])[0] == 0
    reports: list[FolderResult] = []
    status = complete_folder(FolderRun(input_dir=str(data), out_dir=str(tmp_path / "lib"), make_model=_model,
                                       report=reports.append))
    assert status == 0
    assert files(tmp_path / "lib") == sorted([png(0), png(1), RUN_RECORD])
    same_pngs(tmp_path / "cli", tmp_path / "lib")
    (result,) = reports
    assert result.written == 2 and result.total == 2 and not result.failed and not result.skipped


def test_complete_folder_refuses_a_bad_frame_naming_it_and_writes_nothing(tmp_path):
    data = write_folder(tmp_path / "val_selection_cropped", 2, bad={1: "zero sparse"})
    options = FolderRun(input_dir=str(data), out_dir=str(tmp_path / "out"), make_model=_model)
    with pytest.raises(InputError, match=r"^frame 2/2 .*\[1 of 2 frame\(s\) of --input-dir .* bad; nothing written"):
        complete_folder(options)
    assert not (tmp_path / "out").exists()


def test_skipped_frames_raises_the_first_with_the_count_or_keeps_them():
    bad = [(1, InputError, "frame 2/3 b: sparse: no point"), (2, FileNotFoundError, "frame 3/3 c: no such file")]
    with pytest.raises(InputError, match=r"^frame 2/3 b: sparse: no point \[2 of 3 frame\(s\) of --input-dir D bad"):
        skipped_frames(bad, 3, "--input-dir D", skip_bad=False)
    assert skipped_frames(bad, 3, "--input-dir D", skip_bad=True) == {1: bad[0][2], 2: bad[1][2]}
    with pytest.raises(InputError, match="all 2 frame"):
        skipped_frames(bad, 2, "--input-dir D", skip_bad=True)


def test_run_record_holds_what_decides_the_bytes():
    model = _model(True)
    record = functools.partial(run_record, model, True, device="cpu", vis=False, vis_range=None)
    one, two = record(batch_size=1), record(batch_size=2)
    assert one["batch_size"] == 1 and two["batch_size"] == 2 and one["std"] is True and one["device"] == "cpu"
    assert {k: v for k, v in one.items() if k != "batch_size"} == {k: v for k, v in two.items() if k != "batch_size"}
    assert len(one["weights_sha256"]) == 64 and one["dtype"] == "float32"

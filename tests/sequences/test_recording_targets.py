"""crfdepth.sequences.make_targets called from Python: the same files as ``crfdepth targets``, and its checks."""

from __future__ import annotations

from pathlib import Path

import pytest

from crfdepth.cli import main
from crfdepth.data.synthetic import make_sequence
from crfdepth.errors import InputError
from crfdepth.pictures.figures import targets_picture
from crfdepth.sequences import DriveTargets, make_targets
from tests.sequence_drive import DRIVE, poses_file, write_drive


@pytest.fixture(scope="module")
def drive(tmp_path_factory) -> Path:
    return write_drive(tmp_path_factory.mktemp("drive"), make_sequence(6, seed=3))


def _files(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


def test_make_targets_writes_what_the_command_writes(drive, tmp_path):
    poses = poses_file(drive)
    assert main(["targets", "--drive", str(drive), "--poses", str(poses), "-k", "2", "--frames", "1:4", "--out-dir",
                 str(tmp_path / "cli"), "--vis", str(tmp_path / "cli_vis"), "--quiet"]) == 0
    done = make_targets(tmp_path / "lib", drive=drive, poses=str(poses), window=2, frames=(1, 4),
                        vis_dir=tmp_path / "lib_vis", picture=targets_picture)
    assert isinstance(done, DriveTargets)
    assert (done.frames, done.camera, done.out) == (4, "image_02", tmp_path / "lib" / DRIVE)
    assert done.source == f"poses file {poses}" and 0 < done.scan_density < done.density < 1
    cli, lib = _files(tmp_path / "cli"), _files(tmp_path / "lib")
    assert len(cli) == 2 + 2 * 4 and cli == lib  # poses.txt, the index, 4 depth and 4 support PNGs
    assert _files(tmp_path / "cli_vis") == _files(tmp_path / "lib_vis") and len(_files(tmp_path / "lib_vis")) == 4


def test_progress_is_told_each_frame(drive, tmp_path):
    calls = []
    make_targets(tmp_path, drive=drive, poses=str(poses_file(drive)), window=1, progress=lambda *a: calls.append(a))
    assert calls == [(k, 6) for k in range(7)]


@pytest.mark.parametrize("options, named", [
    ({"window": -1}, "window: expected an integer >= 0, got -1"),
    ({"camera": 4}, "camera: expected 2 or 3"),
    ({"frames": (3, 1)}, "frames: expected (A, B)"),
    ({"max_dt": 0.0}, "max_dt: expected a number > 0"),
    ({"poses": "tf"}, "--poses tf: expected auto, odometry, oxts or a poses file with --drive"),
    ({"bag": "x.bag"}, "--drive / --bag: expected one of them"),
    ({"vis_dir": "vis"}, "picture: expected a function"),
])
def test_bad_options_are_refused_naming_them(drive, tmp_path, options, named):
    with pytest.raises(InputError) as caught:
        make_targets(tmp_path / "out", drive=drive, **options)
    assert str(caught.value).startswith(named), caught.value
    assert not (tmp_path / "out").exists()


def test_a_poses_value_that_is_neither_a_keyword_nor_a_file_is_told_what_the_option_takes(drive, tmp_path):
    with pytest.raises(InputError, match=r"^--poses odometr: expected auto, odometry, oxts or the path of a KITTI "
                                         r"odometry poses.txt, got 'odometr', which is neither \(no such file\)"):
        make_targets(tmp_path / "out", drive=drive, poses="odometr")
    assert not (tmp_path / "out").exists()
    with pytest.raises(InputError, match=r"^--out-dir: .* is inside the input drive"):
        make_targets(drive / "out", drive=drive)


def test_a_bag_is_written_as_the_command_writes_it(tmp_path):
    pytest.importorskip("rosbags")
    from tests.cli.test_targets_bag import write_bag

    bag = write_bag(tmp_path / "rig.bag", make_sequence(6, seed=3))
    assert main(["targets", "--bag", str(bag), "-k", "2", "--out-dir", str(tmp_path / "cli"), "--quiet"]) == 0
    done = make_targets(tmp_path / "lib", bag=bag, window=2)
    assert done.drive.parent.parent == tmp_path / "lib" and done.out == tmp_path / "lib" / "rig_sync"
    assert done.source == "/tf odometry odom -> velodyne" and done.frames == 6
    assert _files(tmp_path / "cli") == _files(tmp_path / "lib")

"""Tests of crfdepth.data.kitti.drive: a raw drive's frames for completion, on a small synthetic drive
(tests/sequence_drive.py) and on the shared KITTI drives; the missing files named."""

from __future__ import annotations

import re

import pytest
import torch

from crfdepth.data.kitti import KittiDrive, is_raw_drive, raw_drives
from crfdepth.data.synthetic import make_sequence
from crfdepth.errors import InputError
from crfdepth.geometry.projection import project_velodyne
from crfdepth.io.calibration import read_raw_calibration
from crfdepth.io.kitti import read_depth_png, read_velodyne
from tests.sequence_drive import stem, write_drive

SIZE = (48, 160)


@pytest.fixture(scope="module")
def sequence():
    return make_sequence(3, 0, height=SIZE[0], width=SIZE[1], beams=16)


def test_every_scan_is_a_frame_projected_whole_into_the_uncropped_image(sequence, tmp_path):
    drive = write_drive(tmp_path, sequence)
    dataset = KittiDrive(drive)
    assert len(dataset) == 3 and dataset.names == [stem(i) for i in range(3)]
    calib = read_raw_calibration(drive.parent)
    for i, sample in enumerate(dataset):
        expected = project_velodyne(read_velodyne(drive / "velodyne_points" / "data" / f"{stem(i)}.bin"), calib, SIZE)
        assert sample.image.shape == (3, *SIZE) and sample.name == stem(i)
        assert torch.equal(sample.sparse[0], torch.from_numpy(expected)) and (expected > 0).sum() > 100
        assert not sample.has_target and not sample.target.any()
        assert torch.allclose(sample.K, torch.from_numpy(sequence[0].K).float())
    assert dataset.image_path(1) == drive / "image_02" / "data" / f"{stem(1)}.png"


def test_a_scan_without_its_image_or_a_day_without_calibration_is_named(sequence, tmp_path):
    drive = write_drive(tmp_path, sequence)
    image = drive / "image_02" / "data" / f"{stem(1)}.png"
    image.unlink()
    with pytest.raises(InputError) as info:
        KittiDrive(drive)
    assert str(info.value) == (f"KittiDrive: missing RGB image for {drive / 'velodyne_points' / 'data' / stem(1)}.bin: "
                               f"expected {image}")
    (drive / "velodyne_points" / "data" / f"{stem(1)}.bin").unlink()  # an image without a scan is no frame
    assert KittiDrive(drive).names == [stem(0), stem(2)]
    (drive.parent / "calib_velo_to_cam.txt").unlink()
    with pytest.raises(InputError, match=re.escape(f"KittiDrive: missing calibration of {drive}: no such file: "
                                                   f"{drive.parent / 'calib_velo_to_cam.txt'} (the day folder")):
        KittiDrive(drive)


def test_a_day_folder_or_a_drive_without_scans_is_refused(sequence, tmp_path):
    drive = write_drive(tmp_path, sequence, frames=[0])
    day = drive.parent
    assert is_raw_drive(drive) and not is_raw_drive(day) and raw_drives(day) == [drive]
    with pytest.raises(InputError, match=re.escape(f"got the day folder {day} holding 1 drive(s) ({drive.name}); "
                                                   f"give a drive folder, e.g. {drive}")):
        KittiDrive(day)
    for path in (drive / "velodyne_points" / "data").iterdir():
        path.unlink()
    with pytest.raises(InputError, match="KittiDrive: found no frames under .* velodyne_points/data/\\*.bin"):
        KittiDrive(drive)
    with pytest.raises(InputError, match="camera: expected 2 or 3"):
        KittiDrive(drive, camera=1)


def test_an_image_of_another_size_than_the_calibration_is_named(sequence, tmp_path):
    drive = write_drive(tmp_path, sequence, frames=[0])
    day = drive.parent
    text = (day / "calib_cam_to_cam.txt").read_text()
    (day / "calib_cam_to_cam.txt").write_text(text.replace(f"S_rect_02: {SIZE[1]} {SIZE[0]}", "S_rect_02: 1242 375"))
    with pytest.raises(InputError, match=f"0000000000: image .*{stem(0)}.png is 160x48 \\(WxH\\), expected the "
                                         f"calibration's 1242x375 \\(S_rect_02 in"):
        KittiDrive(drive)[0]


def test_shared_drive_frame_matches_the_published_projection_counts(kitti_root):
    """Drive 0001 frame 5 (kitti README: 19,137 returns in image 02 against 19,154 in KITTI's velodyne_raw);
    camera 3 close to its velodyne_raw too."""
    drive = kitti_root / "raw" / "2011_09_26" / "2011_09_26_drive_0001_sync"
    official = kitti_root / "depth_completion" / "data_depth_velodyne" / "train" / drive.name / "proj_depth" / \
        "velodyne_raw"
    for camera, count in ((2, 19137), (3, None)):
        dataset = KittiDrive(drive, camera=camera)
        assert dataset.names == ["0000000005"]
        sample = dataset[0]
        assert sample.image.shape == (3, 375, 1242)
        pixels = int((sample.sparse > 0).sum())
        published = int((read_depth_png(official / f"image_0{camera}" / "0000000005.png") > 0).sum())
        # camera 2: the README's count within 10 pixels (a return on a pixel border may round either way on
        # another CPU); camera 3: within 1% of KITTI's own projection
        assert abs(pixels - count) <= 10 if count else abs(pixels - published) < 0.01 * published, (camera, pixels,
                                                                                                     published)
        valid = sample.sparse[sample.sparse > 0]
        assert 1.0 < float(valid.min()) and float(valid.max()) < 100.0 and 5.0 < float(valid.median()) < 40.0
    with pytest.raises(InputError, match="holding 2 drive\\(s\\)"):
        KittiDrive(drive.parent)

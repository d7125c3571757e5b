"""A poses file (KITTI odometry ``poses.txt``) or oxts packets with an impossible pose are refused, naming the
file and the line, as a bag's ``/tf`` odometry is (crfdepth.sequences.pose_checks.check_poses)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from crfdepth.errors import InputError
from crfdepth.sequences.pose_source import _read_poses_file
from crfdepth.sequences.poses import read_kitti_poses, read_oxts


def _line(t: float, yaw_deg: float = 0.0, scale: float = 1.0, value: float | None = None) -> str:
    """A camera-0 pose 1 line: rotation about y by ``yaw_deg`` (times ``scale``), ``t`` metres forward (z)."""
    c, s = math.cos(math.radians(yaw_deg)), math.sin(math.radians(yaw_deg))
    m = np.array([[c, 0, s, 0.0], [0, 1, 0, 0.0], [-s, 0, c, t]])
    m[:, :3] *= scale
    if value is not None:
        m[0, 3] = value
    return " ".join(f"{v:.9e}" for v in m.ravel())


def _write(tmp_path, lines: list[str]):
    path = tmp_path / "poses.txt"
    path.write_text("\n".join(lines) + "\n")
    return path


def test_smooth_poses_are_read(tmp_path):
    path = _write(tmp_path, [_line(1.0 * k) for k in range(6)])  # 1 m per frame: 10 m/s at 10 Hz
    assert read_kitti_poses(path, rate=10.0).shape == (6, 4, 4)
    assert read_kitti_poses(path).shape == (6, 4, 4)


def test_a_jump_of_1_km_is_refused_without_a_rate(tmp_path):
    lines = [_line(1.0 * k) for k in range(6)]
    lines[3] = _line(1000.0)
    path = _write(tmp_path, lines)
    with pytest.raises(InputError) as e:
        read_kitti_poses(path)
    assert str(e.value).startswith(f"poses: expected poses without impossible steps in {path}, got 2 failed step(s) "
                                   "(line 4: moved 998.00 m in one step (> 100 m between consecutive poses)")


def test_a_jump_at_a_known_rate_is_refused_as_tf_is(tmp_path):
    lines = [_line(1.0 * k) for k in range(8)]
    lines[4] = _line(3.0 + 9.0)  # 9 m in a 0.1 s step: 90 m/s
    path = _write(tmp_path, lines)
    read_kitti_poses(path)  # under 100 m: fine when the rate is unknown
    with pytest.raises(InputError) as e:
        read_kitti_poses(path, rate=10.0)
    assert str(e.value).startswith(f"poses: expected poses without impossible steps in {path}, got ")
    assert "line 5: moved 9.00 m in one step (> 4.00 m at max_speed 40 m/s)" in str(e.value)


def test_the_poses_option_names_the_file_and_line(tmp_path):
    lines = [_line(1.0 * k) for k in range(6)]
    lines[2] = _line(2000.0)
    path = _write(tmp_path, lines)
    with pytest.raises(InputError) as e:
        _read_poses_file(str(path), "auto, odometry, oxts", rate=10.0)
    assert str(e.value).startswith(f"--poses {path}: expected poses without impossible steps in {path}, got ")
    assert "line 3: moved" in str(e.value)


@pytest.mark.parametrize("line, first", [
    (_line(2.0, scale=1.5), "poses: expected rigid poses (an orthonormal rotation) in {p}, got max |R^T R - I| = 1.25"),
    (_line(2.0, scale=-1.0), "poses: expected rigid poses (an orthonormal rotation) in {p}, got max |R^T R - I| = 0"),
    (_line(2.0, value=float("nan")), "poses: expected finite numbers in {p}, got a non-finite value on line 3"),
    (_line(2.0, value=float("inf")), "poses: expected finite numbers in {p}, got a non-finite value on line 3"),
])
def test_a_non_rigid_or_non_finite_pose_is_refused(tmp_path, line, first):
    lines = [_line(1.0 * k) for k in range(5)]
    lines[2] = line
    path = _write(tmp_path, lines)
    with pytest.raises(InputError) as e:
        read_kitti_poses(path)
    assert str(e.value).startswith(first.format(p=path))
    assert "line 3" in str(e.value)


def _oxts(tmp_path, lats: list[float]):
    data = tmp_path / "oxts" / "data"
    data.mkdir(parents=True)
    for k, lat in enumerate(lats):
        (data / f"{k:010d}.txt").write_text(" ".join(f"{v:.12f}" for v in [lat, 8.4, 110.0, 0, 0, 0] + [0.0] * 24))
    return data


def test_oxts_with_a_jump_is_refused_naming_the_file(tmp_path):
    lats = [49.0 + 1e-5 * k for k in range(5)]  # about 1.1 m a packet
    lats[3] = 49.1  # about 11 km away
    data = _oxts(tmp_path, lats)
    with pytest.raises(InputError) as e:
        read_oxts(data.parent)
    assert str(e.value).startswith(f"oxts: expected poses without impossible steps in {data}, got 2 failed step(s) "
                                   "(file 0000000003.txt: moved ")

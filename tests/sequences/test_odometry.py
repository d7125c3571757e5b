"""crfdepth.sequences odometry, pose_checks, registration and poses: KISS-ICP LiDAR odometry checked
against true poses, the failure check, the registration check, and the readers of given poses (KITTI
poses.txt, KITTI raw oxts)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from crfdepth.data.synthetic import make_sequence
from crfdepth.errors import InputError
from crfdepth.geometry.rigid import camera_relative_pose, invert_rigid, rotation_deg
from crfdepth.sequences.odometry import lidar_odometry, lidar_odometry_with_fallback
from crfdepth.sequences.pose_checks import check_poses
from crfdepth.sequences.poses import oxts_to_pose, read_kitti_poses, read_oxts
from crfdepth.sequences.registration import ground_plane, scan_structure, step_alignment

SPEED, RATE = 10.0, 10.0


def _rot_z(deg):
    a = math.radians(deg)
    R = np.eye(4)
    R[:2, :2] = [[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]]
    return R


def _step_errors(truth, estimate):
    """Per-step translation (m) and rotation (deg) errors of relative motions."""
    te, re = [], []
    for k in range(1, len(truth)):
        d = invert_rigid(invert_rigid(truth[k - 1]) @ truth[k]) @ (invert_rigid(estimate[k - 1]) @ estimate[k])
        te.append(float(np.linalg.norm(d[:3, 3])))
        re.append(rotation_deg(d[:3, :3]))
    return np.array(te), np.array(re)


@pytest.fixture(scope="module")
def drive():
    """20 frames at 10 m/s, 64 beams (the camera at a quarter size: only the scans matter)."""
    return make_sequence(20, 0, speed=SPEED, rate=RATE, height=88, width=304)


@pytest.fixture(scope="module")
def first_step():
    I = np.eye(4)
    I[0, 3] = SPEED / RATE  # the LiDAR's x points forward
    return I


def test_kiss_icp_follows_the_true_poses(drive, first_step):
    pytest.importorskip("kiss_icp")
    odo = lidar_odometry([f.points for f in drive], min_z=-1.5, initial_motion=first_step, threads=2)
    te, re = _step_errors(drive.lidar_poses(), odo.poses)
    # measured (seed 0, 20 frames): translation max 4.6 cm, median 1.9 cm; rotation max 0.03 deg
    assert te.max() < 0.08 and np.median(te) < 0.035
    assert re.max() < 0.1
    np.testing.assert_allclose(odo.poses[0], np.eye(4), atol=1e-12)
    np.testing.assert_allclose(odo.speeds, SPEED, atol=0.8)
    assert odo.failures == () and np.all(odo.fitness > 0.9) and np.nanmax(odo.residual) < 0.2
    # the camera's relative pose through the extrinsic equals the true one
    T = drive.T_cam_lidar
    est = odo.camera_relative(3, 8, T)
    true = invert_rigid(drive[3].T_w_cam) @ drive[8].T_w_cam
    assert np.linalg.norm(est[:3, 3] - true[:3, 3]) < 0.2
    assert true[2, 3] == pytest.approx(5.0, abs=1e-9)  # camera 8 sits 5 m ahead (+z) of camera 3


def test_a_failed_first_step_is_reported_by_frame(drive):
    """Without a motion prior KISS-ICP starts from standstill; on this corridor-like street
    its first step stays near zero, and the check names frame 1 instead of accumulating it."""
    pytest.importorskip("kiss_icp")
    scans = [f.points for f in drive]
    odo = lidar_odometry(scans, min_z=-1.5, threads=2, check=False)
    assert [k for k, _ in odo.failures] == [1]
    assert "a jump" in odo.failures[0][1]
    with pytest.raises(InputError) as e:
        lidar_odometry(scans, min_z=-1.5, threads=2)
    assert str(e.value).startswith("scans: expected LiDAR odometry without failures, got a failure at frame(s) 1 (")


def test_shifted_and_degenerate_scans_are_reported_by_frame(drive, first_step):
    pytest.importorskip("kiss_icp")
    scans = [f.points[:, :3].copy() for f in drive]
    scans[12] = scans[12] + np.array([4.0, 0.0, 0.0])  # a scan from another place
    scans[6] = scans[6][:300]  # a degenerate scan
    odo = lidar_odometry(scans, min_z=-1.5, initial_motion=first_step, threads=2, check=False)
    frames = {k for k, _ in odo.failures}
    assert 6 in frames and 12 in frames and frames <= {6, 7, 12, 13}
    assert any("a degenerate scan" in why for k, why in odo.failures if k == 6)


def _with_error(T, dx, deg):
    """``T`` followed by a step error of ``dx`` metres along x and ``deg`` degrees about z."""
    E = _rot_z(deg)
    E[0, 3] = dx
    return T @ E


def test_the_defaults_slide_on_the_flat_street_and_the_check_names_every_frame(drive):
    """All points, no motion prior: KISS-ICP stays near zero motion (about 1 m short per 1 m step,
    smooth enough that no speed or jump check fires); the alignment check fails every step."""
    pytest.importorskip("kiss_icp")
    scans = [f.points for f in drive]
    odo = lidar_odometry(scans, threads=2, check=False)
    te, _ = _step_errors(drive.lidar_poses(), odo.poses)
    assert np.median(te) > 0.8  # measured: 0.97-1.04 m per 1 m step
    assert [k for k, _ in odo.failures] == list(range(1, len(drive)))
    assert all("the registration slid" in why for _, why in odo.failures)
    # measured: every step's best shift at the search's edge, +1 m along x (the true step is 1 m)
    assert np.all(odo.alignment[1:, 0] > 0.9) and np.abs(odo.alignment[1:, 1]).max() < 0.1
    with pytest.raises(InputError) as e:
        lidar_odometry(scans, threads=2)
    message = str(e.value)
    assert message.startswith("scans: expected LiDAR odometry without failures, got a failure at frame(s) 1 (the "
                              "registration slid: the scan's structure fits the previous scan best at least +1.00 m "
                              "along x from the estimate (limit 0.3 m, 0.5 deg; ")
    assert message.endswith("and 14 more; for a flat ground give min_z (drop it) and initial_motion, or give the "
                            "poses")


def test_alignment_of_true_poses_and_of_injected_errors(drive):
    """True poses: the best offset is the estimate (measured at most 0.05 m, 0.01 deg); a 1 m and/or
    5 deg error injected into one step is found (offsets at the search's edges, 1 m and 2 deg)."""
    truth = drive.lidar_poses()
    structure = [scan_structure(f.points) for f in drive]
    plane = ground_plane(drive[0].points)
    assert plane is not None and plane[0][2] > 0.99 and -1.8 < plane[1] < -1.6  # the LiDAR is 1.73 m up
    normal, height = plane
    # the ground (and the 0.15 m sidewalks) out: measured 42-44 k of 125 k returns kept, none near the plane
    assert all(30000 < len(s) < 0.5 * len(f.points) for s, f in zip(structure, drive))
    assert all(np.mean(np.abs(s @ normal - height) < 0.2) < 0.01 for s in structure)
    steps = [invert_rigid(truth[k - 1]) @ truth[k] for k in range(1, len(truth))]
    found = [step_alignment(structure[k - 1], structure[k], steps[k - 1]) for k in range(1, len(truth))]
    offsets = np.array([a.offset for a in found])
    assert np.abs(offsets[:, :2]).max() < 0.12 and np.abs(offsets[:, 2]).max() < 0.1
    assert all(a.failure() is None for a in found)
    assert check_poses(truth, alignment=[None] + found) == []
    for k in (5, 12):
        shifted = step_alignment(structure[k - 1], structure[k], _with_error(steps[k - 1], 1.0, 0.0))
        assert shifted.offset[0] == pytest.approx(-1.0, abs=0.15) and shifted.failure() is not None
        turned = step_alignment(structure[k - 1], structure[k], _with_error(steps[k - 1], 0.0, 5.0))
        assert turned.offset[2] <= -1.9 and "deg about z" in turned.failure()
        both = step_alignment(structure[k - 1], structure[k], _with_error(steps[k - 1], 1.0, 5.0))
        assert both.failure() is not None and both.best < both.residual
    bad = list(found)
    bad[6] = step_alignment(structure[6], structure[7], _with_error(steps[6], 1.0, 5.0))  # frame 7
    fails = check_poses(truth, alignment=[None] + bad)
    assert [k for k, _ in fails] == [7] and fails[0][1].startswith("the registration slid: ")


def test_the_fallback_drops_the_ground_and_follows_the_true_poses(drive):
    pytest.importorskip("kiss_icp")
    odo, note = lidar_odometry_with_fallback([f.points for f in drive], threads=2)
    assert odo.failures == ()
    assert note.startswith("the full scans' registration slid, so points below z = -1.3")
    te, re = _step_errors(drive.lidar_poses(), odo.poses)
    # measured (20 frames at 10 m/s): at most 11 cm per step, median 2.4 cm
    assert te.max() < 0.2 and np.median(te) < 0.05 and re.max() < 0.1
    with pytest.raises(InputError, match=r"^min_z: expected to be left to lidar_odometry_with_fallback, got -1.5$"):
        lidar_odometry_with_fallback([f.points for f in drive], min_z=-1.5)


def test_check_poses_by_hand():
    poses = [np.eye(4)]
    for k in range(1, 10):
        T = poses[-1].copy()
        T[0, 3] += 1.0
        poses.append(T)
    assert check_poses(poses) == []
    bad = [P.copy() for P in poses]
    for P in bad[5:]:
        P[0, 3] += 2.5  # a jump of 2.5 m at frame 5
    fails = check_poses(bad)
    assert [k for k, _ in fails] == [5]
    assert fails[0][1] == "step of 3.50 m against 1.00 m for its neighbours (a jump)"
    fast = [P @ np.diag([1.0, 1, 1, 1]) for P in poses]
    fast[9] = fast[8] @ _rot_z(8.0)
    assert [k for k, _ in check_poses(fast)] == [9]
    assert "turned 8.00 deg in one step (> 6.00 deg" in check_poses(fast)[0][1]


def test_camera_relative_pose_formula():
    rng = np.random.default_rng(0)
    T_cam_lidar = _rot_z(30.0)
    T_cam_lidar[:3, 3] = [0.1, -0.2, 0.3]
    s, t = _rot_z(3.0), _rot_z(-4.0)
    s[:3, 3], t[:3, 3] = rng.normal(size=3), rng.normal(size=3)
    rel = camera_relative_pose(s, t, T_cam_lidar)
    p_lidar_t = np.array([5.0, 1.0, -1.0, 1.0])
    # the same point through the world: camera t -> camera s
    p_cam_t = T_cam_lidar @ p_lidar_t
    p_cam_s = T_cam_lidar @ invert_rigid(s) @ t @ p_lidar_t
    np.testing.assert_allclose(rel @ p_cam_t, p_cam_s, atol=1e-12)


def test_without_kiss_icp_the_message_names_the_extra(monkeypatch):
    import builtins

    real_import = builtins.__import__

    def fake_import(name, *args, **kwargs):
        if name.startswith("kiss_icp"):
            raise ImportError("no kiss_icp")
        return real_import(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", fake_import)
    with pytest.raises(InputError) as e:
        lidar_odometry([np.zeros((10, 3)), np.zeros((10, 3))])
    assert str(e.value) == ('lidar_odometry: expected the kiss-icp package (LiDAR odometry), got it not '
                            'installed; pip install "crfdepth[odometry]"')


def test_bad_scans():
    pytest.importorskip("kiss_icp")
    with pytest.raises(InputError, match=r"^scans: expected at least 2 scans for odometry, got 1$"):
        lidar_odometry([np.zeros((10, 3))])
    with pytest.raises(InputError, match=r"^scans\[1\]: expected \(N, 3\) or \(N, 4\) points, got an array of shape \(10, 2\)"):
        lidar_odometry([np.zeros((10, 3)), np.zeros((10, 2))])


# --------------------------------------------------------------------------- poses given


def _pose_lines(poses):
    return "\n".join(" ".join(f"{v:.9e}" for v in P[:3].ravel()) for P in poses) + "\n"


def test_kitti_poses_round_trip(tmp_path, drive):
    cams = drive.camera_poses()  # KITTI odometry's convention: camera poses, the first identity
    path = tmp_path / "poses.txt"
    path.write_text(_pose_lines(cams))
    np.testing.assert_allclose(read_kitti_poses(path), cams, atol=1e-8)
    lidar = read_kitti_poses(path, drive.T_cam_lidar, n_frames=15)
    assert lidar.shape == (15, 4, 4)
    np.testing.assert_allclose(lidar, drive.lidar_poses()[:15], atol=1e-8)


@pytest.mark.parametrize("text,message", [
    ("1 0 0 0 0 1 0 0 0 0 1\n", "poses: expected 12 numbers per line in {p}, got 11 on line 1"),
    ("1 0 0 0 0 1 0 0 0 0 1 0\n1 0 0 0 0 1 0 0 0 0 1 x\n", "poses: expected numbers in {p}, got "),
    ("1 0 0 0 0 1 0 0 0 0 1 0\n2 0 0 0 0 1 0 0 0 0 1 0\n",
     "poses: expected rigid poses (an orthonormal rotation) in {p}, got max |R^T R - I| = 3, det 2 on line 2"),
    ("1 0 0 0 0 1 0 0 0 0 1 0\n", "poses: expected at least 3 poses (one per frame) in {p}, got 1"),
    ("\n", "poses: expected 12 numbers per line in {p}, got an empty file"),
])
def test_kitti_poses_bad_input(tmp_path, text, message):
    path = tmp_path / "poses.txt"
    path.write_text(text)
    with pytest.raises(InputError) as e:
        read_kitti_poses(path, n_frames=3)
    assert str(e.value).startswith(message.format(p=path))


def _oxts_line(lat, lon, alt, roll, pitch, yaw):
    return " ".join(f"{v:.12f}" for v in [lat, lon, alt, roll, pitch, yaw] + [0.0] * 24) + "\n"


def test_oxts_devkit_conversion(tmp_path):
    """Driving 10 m north along a meridian, heading north (yaw = 90 deg from east): in the LiDAR
    frame of the first packet the car moves 10 m forward (+x)."""
    lat0, lon0, er = 49.0, 8.4, 6378137.0
    scale = math.cos(math.radians(lat0))
    data = tmp_path / "oxts" / "data"
    data.mkdir(parents=True)
    # latitude step that moves the Mercator y by 10 m: y = scale er log(tan((90 + lat) pi / 360))
    y0 = scale * er * math.log(math.tan((90 + lat0) * math.pi / 360))
    for k in range(3):
        lat = math.degrees(2 * math.atan(math.exp((y0 + 10.0 * k) / (scale * er)))) - 90
        (data / f"{k:010d}.txt").write_text(_oxts_line(lat, lon0, 112.0, 0.0, 0.0, math.pi / 2))
    imu = read_oxts(tmp_path / "oxts")
    np.testing.assert_allclose(imu[:, :3, 3], [[0, 0, 0], [10, 0, 0], [20, 0, 0]], atol=1e-6)
    T_velo_imu = np.eye(4)
    T_velo_imu[:3, 3] = [-0.81, 0.32, -0.80]  # KITTI's IMU -> Velodyne offset, no rotation
    lidar = read_oxts(tmp_path / "oxts" / "data", T_velo_imu @ _rot_z(0.0), n_frames=2)
    assert lidar.shape == (2, 4, 4)
    np.testing.assert_allclose(lidar[1, :3, 3], [10, 0, 0], atol=1e-6)
    # a turn of the IMU shows as the same turn of the LiDAR
    P = oxts_to_pose(np.r_[lat0, lon0, 0.0, 0.0, 0.0, 0.3, np.zeros(24)], scale)
    assert rotation_deg(P[:3, :3]) == pytest.approx(math.degrees(0.3), abs=1e-9)


def test_oxts_bad_input(tmp_path):
    data = tmp_path / "data"
    data.mkdir()
    (data / "0000000000.txt").write_text(_oxts_line(49.0, 8.4, 100.0, 0, 0, 0))
    (data / "0000000001.txt").write_text("49.0 8.4 100.0\n")
    with pytest.raises(InputError) as e:
        read_oxts(data)
    assert str(e.value) == f"oxts: expected 30 numbers per line in {data / '0000000001.txt'}, got 3 on line 1"
    (data / "0000000001.txt").write_text(_oxts_line(49.0, 8.4, 100.0, 0, 0, 0))
    with pytest.raises(InputError) as e:
        read_oxts(data, n_frames=5)
    assert str(e.value) == f"oxts: expected at least 5 packets (one per frame) in {data}, got 2"
    with pytest.raises(FileNotFoundError, match="oxts: no such directory"):
        read_oxts(tmp_path / "missing")


# --------------------------------------------------------------------------- the real drive

DRIVE = "sequences/2011_09_26/2011_09_26_drive_0060_sync"


@pytest.mark.kitti
def test_kiss_icp_on_the_real_drive(kitti_root):
    """The first 20 scans of a slow drive in dense traffic: forward, slow, straight, no failure."""
    pytest.importorskip("kiss_icp")
    from crfdepth.io.kitti import read_velodyne

    files = sorted((kitti_root / DRIVE / "velodyne_points" / "data").glob("*.bin"))
    assert len(files) == 78
    odo = lidar_odometry([read_velodyne(f) for f in files[:20]], threads=2)
    assert odo.failures == ()
    # measured: 4.0 m forward in 1.9 s (1.1 to 2.6 m/s per step, 2.1 m/s on average)
    x, y, z = odo.poses[-1][:3, 3]
    assert 3.0 < x < 5.0 and abs(y) < 0.3 and abs(z) < 0.2
    assert np.all((odo.speeds > 0.5) & (odo.speeds < 4.0))
    assert odo.step_rotation_deg.max() < 0.2
    assert np.all(odo.fitness > 0.95)
    # the alignment check: measured over all 77 steps at most 0.15 m along x, 0.02 m along y, 0.06 deg
    assert np.abs(odo.alignment[:, :2]).max() < 0.2 and np.abs(odo.alignment[:, 2]).max() < 0.2
    # a 1 m error injected into step 10 is found
    structure = [scan_structure(read_velodyne(f)) for f in files[9:11]]
    step = invert_rigid(odo.poses[9]) @ odo.poses[10]
    assert step_alignment(*structure, step).failure() is None
    wrong = step_alignment(*structure, _with_error(step, 1.0, 0.0))
    assert wrong.offset[0] == pytest.approx(-1.0, abs=0.2) and wrong.failure() is not None

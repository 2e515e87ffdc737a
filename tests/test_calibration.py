"""Camera calibration files (rmavatar.data.calibration): TOML (Pose2Sim, Anipose) against scipy's
rotations, Qualisys against a camera whose view is known by construction, the real Pose2Sim rig (its
cameras see the force plates; MediaPipe's landmarks of two of its videos triangulate to a few pixels),
and bad files refused with their name."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from rmavatar.data.calibration import pick_camera, read_calibration
from rmavatar.utils import UserError

TOML = """
[metadata]
adjusted = false
error = 0.0

[cam_a]
name = "cam_a"
size = [ 1088.0, 1920.0,]
matrix = [ [ 1681.0, 0.0, 540.0,], [ 0.0, 1680.0, 964.0,], [ 0.0, 0.0, 1.0,],]
distortions = [ -0.0007, 0.002, 1e-5, 1e-5,]
rotation = [ 0.3, -1.2, 0.7,]
translation = [ 0.5, 1.0, 4.0,]
fisheye = false
"""


def test_toml_camera_matches_scipy(tmp_path):
    path = tmp_path / "Calib.toml"
    path.write_text(TOML)
    cam = read_calibration(path)["cam_a"]
    np.testing.assert_allclose(cam.R, Rotation.from_rotvec([0.3, -1.2, 0.7]).as_matrix(), atol=1e-12)
    np.testing.assert_allclose(cam.t, [0.5, 1.0, 4.0])
    assert cam.size == (1088, 1920)
    assert cam.K[0, 0] == 1681.0 and cam.K[1, 2] == 964.0
    # a point in front of the camera projects where K says
    X = np.linalg.solve(cam.R, np.array([0.1, -0.2, 3.0]) - cam.t)
    x = cam.K @ (cam.R @ X + cam.t)
    np.testing.assert_allclose(x[:2] / x[2], [540 + 1681 * 0.1 / 3, 964 - 1680 * 0.2 / 3], atol=1e-9)
    np.testing.assert_allclose(cam.scaled_K(544, 960)[0], [840.5, 0.0, 270.0])


def _qca(M, position_mm, K64, size=(1088, 1920), serial="cam01") -> str:
    r = {f"r{i + 1}{j + 1}": M[i][j] for i in range(3) for j in range(3)}
    attrs = " ".join(f'{k}="{v}"' for k, v in r.items())
    x, y, z = position_mm
    fu, cu, cv = K64
    return f"""<?xml version='1.0' encoding='ASCII'?>
<calibration type="regular"><cameras>
 <camera active="1" serial="{serial}" model="none">
  <fov_video bottom="{size[1] - 1}" left="0" right="{size[0] - 1}" top="0"/>
  <transform {attrs} x="{x}" y="{y}" z="{z}"/>
  <intrinsic centerPointU="{cu}" centerPointV="{cv}" focalLengthU="{fu}" focalLengthV="{fu}"
   radialDistortion1="0" radialDistortion2="0" radialDistortion3="0" tangentalDistortion1="0"
   tangentalDistortion2="0"/>
 </camera></cameras></calibration>
"""


def test_qualisys_camera_looks_where_it_was_placed(tmp_path):
    """A Qualisys camera 3 m behind the origin along -y, 1 m up, looking along +y (world z up): its
    r11..r33 hold the camera's axes (x right, y up, looking down its -z) as rows, in world coordinates.
    The point 3 m straight ahead lands on the principal point, a point above it higher in the image
    (smaller v), one to the world's +x to the right."""
    # rows: camera x = world +x, camera y (up) = world +z, camera z = world -y (it looks along +y)
    M = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])
    path = tmp_path / "Calib.qca.txt"
    path.write_text(_qca(M, (0.0, -3000.0, 1000.0), (64 * 1500.0, 64 * 544.0, 64 * 960.0)))
    cam = read_calibration(path)["cam01"]

    def project(X):
        x = cam.K @ (cam.R @ np.asarray(X, float) + cam.t)
        assert x[2] > 0, "behind the camera"
        return x[:2] / x[2]

    np.testing.assert_allclose(project([0, 0, 1]), [544, 960], atol=1e-9)
    u, v = project([0, 0, 1.3])
    assert abs(u - 544) < 1e-9 and v == pytest.approx(960 - 1500 * 0.3 / 3)
    u, v = project([0.3, 0, 1])
    assert u == pytest.approx(544 + 1500 * 0.3 / 3) and abs(v - 960) < 1e-9
    np.testing.assert_allclose(-cam.R.T @ cam.t, [0, -3, 1], atol=1e-12)  # the centre, in metres
    assert cam.size == (1088, 1920)


def test_bad_calibrations_are_refused_by_name(tmp_path):
    bad = tmp_path / "calib.toml"
    bad.write_text("this is = = not toml")
    with pytest.raises(UserError, match="calib.toml.*neither"):
        read_calibration(bad)
    with pytest.raises(UserError, match="missing.toml.*cannot read"):
        read_calibration(tmp_path / "missing.toml")
    partial = tmp_path / "partial.toml"
    partial.write_text('[c]\nmatrix = [[1.0, 0, 0], [0, 1, 0], [0, 0, 1]]\nsize = [4, 4]\n')
    with pytest.raises(UserError, match=r"partial.toml, \[c\] lacks rotation, translation"):
        read_calibration(partial)
    sheared = tmp_path / "Calib.qca.txt"
    sheared.write_text(_qca(np.diag([1.0, 2.0, 1.0]), (0, 0, 0), (64 * 1500.0, 0, 0)))
    with pytest.raises(UserError, match="Calib.qca.txt, camera 'cam01': the rotation is not a rotation"):
        read_calibration(sheared)
    good = tmp_path / "good.toml"
    good.write_text(TOML)
    cams = read_calibration(good)
    with pytest.raises(UserError, match="no camera 'cam9' \\(cameras: cam_a\\)"):
        pick_camera(cams, "cam9", None, good)
    with pytest.raises(UserError, match="no camera is named like the video cam04.mp4"):
        pick_camera(cams, None, "videos/cam04.mp4", good)
    assert pick_camera(cams, None, "cam_a.mp4", good).name == "cam_a"


@pytest.fixture(scope="module")
def pose2sim(request, tmp_path_factory):
    from footage import clip

    cache = request.config.cache.mkdir("rmavatar_footage") if getattr(request.config, "cache", None) is not None \
        else tmp_path_factory.mktemp("footage")
    return lambda name: clip(name, Path(cache))


def test_pose2sim_rig_sees_its_force_plates(pose2sim):
    """The real Pose2Sim demo rig (Qualisys): all four cameras, 1.7-2.1 m up, 2.4-4.5 m from the plates at
    the world's origin, which each of them sees inside its frame."""
    cams = read_calibration(pose2sim("balance_calib"))
    assert sorted(cams) == ["cam01", "cam02", "cam03", "cam04"]
    np.testing.assert_allclose(-cams["cam01"].R.T @ cams["cam01"].t, [1.4602324, -1.9091590, 1.8965059])
    for cam in cams.values():
        centre = -cam.R.T @ cam.t
        assert 1.6 < centre[2] < 2.2 and 2.3 < np.linalg.norm(centre[:2]) < 4.5
        x = cam.K @ cam.t  # the origin
        assert x[2] > 0
        u, v = x[:2] / x[2]
        assert 0 < u < cam.size[0] and 0 < v < cam.size[1], (cam.name, u, v)


def test_pose2sim_landmarks_triangulate(pose2sim):
    """MediaPipe's torso and knee landmarks in frame 30 of cam01 and cam04 triangulate with the rig's
    calibration to within a few pixels (a transposed rotation or an unflipped camera axis gives
    hundreds)."""
    if importlib.util.find_spec("mediapipe") is None:
        pytest.skip("MediaPipe is not installed")
    from rmavatar.capture.detect import Detector
    from rmavatar.capture.frames import frames_at, open_source

    cams = read_calibration(pose2sim("balance_calib"))
    seen = {}
    for name in ("cam01", "cam04"):
        source = open_source(pose2sim(f"balance_{name}" if name != "cam04" else "balance"))
        (_, image), = frames_at(source, [30])
        with Detector() as detect:
            seen[name] = detect.look(image)
        assert seen[name] is not None
    errors = []
    for j in (11, 12, 23, 24, 25, 26):
        rows = []
        for name, det in seen.items():
            P = cams[name].K @ np.hstack([cams[name].R, cams[name].t[:, None]])
            u, v = det.keypoints[j]
            rows += [u * P[2] - P[0], v * P[2] - P[1]]
        X = np.linalg.svd(np.array(rows))[2][-1]
        for name, det in seen.items():
            x = cams[name].K @ (cams[name].R @ (X[:3] / X[3]) + cams[name].t)
            errors.append(np.linalg.norm(x[:2] / x[2] - det.keypoints[j]))
    assert np.median(errors) < 8.0, errors

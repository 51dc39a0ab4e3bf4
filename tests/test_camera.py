import subprocess
import sys

import numpy as np
import pytest

from rgbd_gt.camera import Camera, backproject, project, rescale, undistort_image, without_distortion
from rgbd_gt.errors import InputError
from rgbd_gt.io import read_camera, write_camera
from rgbd_gt.io.camera_file import check_image_matches

CAM = Camera(640, 480, 520.0, 515.0, 321.3, 238.7, (-0.21, 0.08, 0.0012, -0.0007, -0.015))


def test_yaml_round_trip(tmp_path):
    write_camera(tmp_path / "c.yaml", CAM)
    assert read_camera(tmp_path / "c.yaml") == CAM


@pytest.mark.parametrize("n", [4, 5, 8])
def test_distortion_lengths(tmp_path, n):
    (tmp_path / "c.yaml").write_text(
        f"width: 640\nheight: 480\nfx: 500\nfy: 500\ncx: 320\ncy: 240\ndistortion: {[0.01] * n}\n"
    )
    assert len(read_camera(tmp_path / "c.yaml").distortion) == n


def test_opencv_calibration_file(tmp_path):
    import cv2

    path = str(tmp_path / "calib.yml")
    fs = cv2.FileStorage(path, cv2.FILE_STORAGE_WRITE)
    fs.write("image_width", 640)
    fs.write("image_height", 480)
    fs.write("camera_matrix", CAM.K)
    fs.write("distortion_coefficients", np.array(CAM.distortion).reshape(1, 5))
    fs.release()
    cam = read_camera(path)
    assert cam.size == (640, 480)
    np.testing.assert_allclose(cam.K, CAM.K)
    np.testing.assert_allclose(cam.distortion, CAM.distortion)


def test_ros_camera_info_yaml(tmp_path):
    d = CAM.distortion
    (tmp_path / "ost.yaml").write_text(f"""image_width: 640
image_height: 480
camera_name: narrow_stereo
camera_matrix:
  rows: 3
  cols: 3
  data: [{CAM.fx}, 0.0, {CAM.cx}, 0.0, {CAM.fy}, {CAM.cy}, 0.0, 0.0, 1.0]
distortion_model: plumb_bob
distortion_coefficients:
  rows: 1
  cols: 5
  data: {list(d)}
rectification_matrix: {{rows: 3, cols: 3, data: [1, 0, 0, 0, 1, 0, 0, 0, 1]}}
""")
    assert read_camera(tmp_path / "ost.yaml") == CAM
    text = (tmp_path / "ost.yaml").read_text()
    for bad, needle in ((text.replace("plumb_bob", "equidistant"), "equidistant"),
                        (text.replace("data: [520.0, 0.0", "data: [0.0"), "camera_matrix.data must be 9"),
                        (text.replace("image_height: 480", "image_height: -1"), "height must be a whole number")):
        (tmp_path / "bad.yaml").write_text(bad)
        with pytest.raises(InputError, match=needle):
            read_camera(tmp_path / "bad.yaml")


def test_koide3_calib_json(tmp_path):
    import json

    from rgbd_gt.io import read_pose

    calib = {"camera": {"camera_model": "plumb_bob", "distortion_coeffs": list(CAM.distortion),
                        "intrinsics": [CAM.fx, CAM.fy, CAM.cx, CAM.cy]},
             "meta": {"intensity_channel": "intensity"},
             # the camera's pose in the LiDAR frame: a LiDAR looking along x, a camera along z, 10 cm apart
             "results": {"init_T_lidar_camera": [0.1, -0.03, -0.09, -0.5, 0.5, -0.5, 0.5]}}
    path = tmp_path / "calib.json"
    path.write_text(json.dumps(calib))
    assert read_camera(path, (640, 480)) == CAM
    T, meta = read_pose(path)
    assert meta == {}
    np.testing.assert_allclose(T[:3, :3] @ [1, 0, 0], [0, 0, 1], atol=1e-12)  # LiDAR forward is the camera's z
    np.testing.assert_allclose(T[:3, :3] @ [0.1, -0.03, -0.09] + T[:3, 3], 0, atol=1e-12)  # the camera centre
    calib["results"]["T_lidar_camera"] = [0, 0, 0, 0, 0, 0, 1]  # the calibrated result wins over the init
    path.write_text(json.dumps(calib))
    np.testing.assert_allclose(read_pose(path)[0], np.eye(4))
    pose, camera = read_pose, lambda p: read_camera(p, (640, 480))
    for change, reader, needle in ((lambda c: c["results"].update(T_lidar_camera=[0, 0, 0, 0, 0, 0, 2]), pose, "length is 2"),
                                   (lambda c: c["results"].update(T_lidar_camera=[0, 0, 0]), pose, "7 finite numbers"),
                                   (lambda c: c.pop("results"), pose, "no extrinsic"),
                                   (lambda c: c["camera"].update(camera_model="fisheye"), camera, "fisheye"),
                                   (lambda c: c["camera"].update(intrinsics=[1, "a", 3, 4]), camera, "4 finite numbers")):
        bad = json.loads(json.dumps(calib))
        change(bad)
        path.write_text(json.dumps(bad))
        with pytest.raises(InputError, match=needle):
            reader(path)
    path.write_text("{not json")
    with pytest.raises(InputError, match="invalid JSON"):
        read_pose(path)
    with pytest.raises(InputError, match="no image size"):
        read_camera(path)


def _pjlab3_depth(folder, *args) -> np.ndarray:
    """export-depth of pjlab_3's sweep with these camera, pose and image arguments: the depth map."""
    from conftest import DATA, run_cli
    from rgbd_gt.io.depth_file import read_depth_exr

    out = folder / f"depth_{len(list(folder.glob('depth_*.exr')))}.exr"
    proc = run_cli("export-depth", "--scan", DATA / "lidar_camera/pjlab_3/calib.pcd", *args, "-o", out)
    assert proc.returncode == 0, proc.stderr
    return read_depth_exr(out)[0]


@pytest.fixture(scope="module")
def pjlab3_depth(tmp_path_factory):
    """pjlab_3's depth map with its own calib.txt, that the same rig in other files must give;
    None without the data."""
    from conftest import DATA

    scene = DATA / "lidar_camera" / "pjlab_3"
    if not scene.exists():
        return None
    depth = _pjlab3_depth(tmp_path_factory.mktemp("pjlab3"), "--camera", scene / "calib.txt", "--image", scene / "calib.png",
                          "--pose", scene / "calib.txt")
    assert (depth > 0).sum() > 5000
    return depth


def test_livox_camera_calib_files(tmp_path, pjlab3_depth):
    """livox_camera_calib's files, written as it writes them, for a real rig (pjlab_3's K, D and
    reference T where the data are present): calib.yaml's camera (no image size), extrinsic.txt
    (4 rows of 4, commas) and the config's initial ExtrinsicMat (OpenCV YAML); all read as
    calib.txt reads the same values."""
    from conftest import DATA
    from rgbd_gt.io import read_pose

    scene = DATA / "lidar_camera" / "pjlab_3"
    size = (1920, 1200)
    cam, T = CAM, np.eye(4)
    if scene.exists():
        cam, T = read_camera(scene / "calib.txt", size), read_pose(scene / "calib.txt")[0]
    else:
        size = (CAM.width, CAM.height)
        T[:3, :3], T[:3, 3] = [[0, -1, 0], [0, 0, -1], [1, 0, 0]], [0.05, -0.1, 0.02]
    K = [cam.fx, 0.0, cam.cx, 0.0, cam.fy, cam.cy, 0.0, 0.0, 1.0]
    (tmp_path / "calib.yaml").write_text(
        'common:\n    image_file: "0.png"\n    pcd_file: "0.pcd"\n    result_file: "extrinsic.txt"\n'
        f"camera:\n    camera_matrix: [{', '.join(map(str, K))}]\n"
        f"    dist_coeffs: [{', '.join(map(str, cam.distortion))}]\n"
        "calib:\n    calib_config_file: config_outdoor.yaml\n    use_rough_calib: true\n")
    assert read_camera(tmp_path / "calib.yaml", size) == cam
    assert read_camera(tmp_path / "calib.yaml", lambda: size) == cam  # the photo read only when needed
    (tmp_path / "camera.yaml").write_text(  # its older camera file: OpenCV YAML with a size
        f"%YAML:1.0\nCameraMat: !!opencv-matrix\n  rows: 3\n  cols: 3\n  dt: d\n  data: {K}\n"
        f"DistCoeffs: !!opencv-matrix\n  rows: {len(cam.distortion)}\n  cols: 1\n  dt: d\n  data: {list(cam.distortion)}\n"
        f"Camera.width: {size[0]}\nCamera.height: {size[1]}\n")
    assert read_camera(tmp_path / "camera.yaml") == cam
    with pytest.raises(InputError, match="no image size"):
        read_camera(tmp_path / "calib.yaml")
    (tmp_path / "extrinsic.txt").write_text("".join(",".join(f"{v:g}" for v in row) + "\n" for row in T))
    np.testing.assert_allclose(read_pose(tmp_path / "extrinsic.txt")[0], T, atol=1e-5)  # printed with 6 digits
    (tmp_path / "saved.txt").write_text("# numpy.savetxt\n" + "".join(" ".join(f"{v:.18e}" for v in row) + "\n" for row in T[:3]))
    np.testing.assert_allclose(read_pose(tmp_path / "saved.txt")[0], T, atol=1e-12)
    data = ",\n         ".join(", ".join(f"{v:.9f}" for v in row) for row in T)
    (tmp_path / "config_outdoor.yaml").write_text(
        '%YAML:1.0\n\nPointCloudTopic: "/livox/lidar"\nData.custom_msg: 0\n\nExtrinsicMat: !!opencv-matrix\n'
        f"  rows: 4\n  cols: 4\n  dt: d\n  data: [{data}]\nCanny.gray_threshold: 10\n")
    np.testing.assert_allclose(read_pose(tmp_path / "config_outdoor.yaml")[0], T, atol=1e-8)
    for name, text, needle in (("rows.txt", "1,0,0\n0,1,0\n0,0,1\n", r"rows of 4 numbers, got rows of \[3, 3, 3\]"),
                               ("nan.txt", "1 0 0 0\n0 1 0 0\n0 0 1 nan\n", "non-finite"),
                               ("empty.txt", "\n", "empty"),
                               ("skew.txt", "1 0.5 0 0\n0 1 0 0\n0 0 1 0\n", "the matrix is not rigid"),
                               ("words.txt", "hello world\n", "not a plain 3x4 or 4x4 matrix"),
                               ("cv.yaml", "%YAML:1.0\nCanny.gray_threshold: 10\n", "no 'ExtrinsicMat'")):
        (tmp_path / name).write_text(text)
        with pytest.raises(InputError, match=needle):
            read_pose(tmp_path / name)
    if scene.exists():  # the files drive a command on the real sweep as calib.txt does
        depth = _pjlab3_depth(tmp_path, "--camera", tmp_path / "calib.yaml", "--image", scene / "calib.png",
                              "--pose", tmp_path / "saved.txt")
        assert np.array_equal(depth, pjlab3_depth)


def _autoware_file(cam: Camera, T_lidar_from_cam: np.ndarray, model: str = "plumb_bob", size=None) -> str:
    """A calibration file as Autoware's camera-LiDAR calibrator writes it (cv::FileStorage of
    OpenCV 3/4, then ImageSize, ReprojectionError and DistModel appended as plain YAML)."""
    def matrix(name, m):
        m = np.atleast_2d(m)
        data = ", ".join(f"{v:.16e}" for v in m.ravel())
        return f"{name}: !!opencv-matrix\n   rows: {m.shape[0]}\n   cols: {m.shape[1]}\n   dt: d\n   data: [ {data} ]\n"
    K = [[cam.fx, 0, cam.cx], [0, cam.fy, cam.cy], [0, 0, 1]]
    size = size or [cam.width, cam.height]
    return ("%YAML:1.0\n---\n" + matrix("CameraExtrinsicMat", T_lidar_from_cam) + matrix("CameraMat", K)
            + matrix("DistCoeff", np.array(cam.distortion)) + f"ImageSize: {size}\nReprojectionError: 0.\nDistModel: {model}\n")


def test_autoware_calibration_file(tmp_path, pjlab3_depth):
    """Autoware's calibration YAML is one file for both: the camera (CameraMat, DistCoeff,
    ImageSize) and the pose, CameraExtrinsicMat being the camera's pose in the LiDAR frame (the
    inverse of T_cam_from_scan). Written for pjlab_3's rig where the data are present, it reads as
    calib.txt reads the same values and drives export-depth to the same depth map."""
    from conftest import DATA
    from rgbd_gt.io import read_pose
    from rgbd_gt.pose import invert

    scene = DATA / "lidar_camera" / "pjlab_3"
    cam, T = CAM, np.eye(4)
    T[:3, :3], T[:3, 3] = [[0, -1, 0], [0, 0, -1], [1, 0, 0]], [0.05, -0.1, 0.02]
    if scene.exists():
        cam, T = read_camera(scene / "calib.txt", (1920, 1200)), read_pose(scene / "calib.txt")[0]
    path = tmp_path / "autoware.yaml"
    path.write_text(_autoware_file(cam, invert(T)))
    assert read_camera(path) == cam
    np.testing.assert_allclose(read_pose(path)[0], T, atol=1e-12)
    for name, text, needle in (("fisheye.yaml", _autoware_file(cam, invert(T), model="equidistant"), "DistModel 'equidistant'"),
                               ("size.yaml", _autoware_file(cam, invert(T), size=[cam.width]), r"ImageSize must be \[width, height\]"),
                               ("nosize.yaml", _autoware_file(cam, invert(T)).replace("ImageSize", "Size"), "or 'ImageSize'"),
                               ("norows.yaml", _autoware_file(cam, invert(T)).replace("   rows: 3\n", ""), "lacks its rows or cols"),
                               # fuzz seed 15: was "got np.float64(1e+30)"
                               ("tall.yaml", _autoware_file(cam, invert(T), size=[cam.width, 1e30]), r"height .* got 1e\+30$")):
        (tmp_path / name).write_text(text)
        with pytest.raises(InputError, match=needle):
            read_camera(tmp_path / name)
    for name, text, needle in (("skew.yaml", _autoware_file(cam, np.diag([1.0, 1.0, 2.0, 1.0])), "not rigid|orthonormal"),
                               ("words.yaml", _autoware_file(cam, invert(T)).replace("0.0000000000000000e+00", "abc", 1),
                                "not a list of numbers")):  # the extrinsic's last row holds the first 0
        (tmp_path / name).write_text(text)
        with pytest.raises(InputError, match=needle):
            read_pose(tmp_path / name)
    if scene.exists():  # no --image: the file holds the size
        assert np.array_equal(_pjlab3_depth(tmp_path, "--camera", path, "--pose", path), pjlab3_depth)


def test_kalibr_camchain(tmp_path):
    """Kalibr's camchain YAML of one camera (pinhole, radtan: OpenCV's k1 k2 p1 p2) reads as a
    camera, and with a T_cam_lidar in its block (LiDAR to camera, as Oxford Spires' cam-lidar.yaml
    writes it) as a pose; pjlab_3's rig drives export-depth where the data are present."""
    import yaml
    from conftest import DATA
    from rgbd_gt.io import read_pose

    scene = DATA / "lidar_camera" / "pjlab_3"
    cam, T = CAM, np.eye(4)
    T[:3, :3], T[:3, 3] = [[0, -1, 0], [0, 0, -1], [1, 0, 0]], [0.05, -0.1, 0.02]
    if scene.exists():
        cam, T = read_camera(scene / "calib.txt", (1920, 1200)), read_pose(scene / "calib.txt")[0]
    cam = Camera(cam.width, cam.height, cam.fx, cam.fy, cam.cx, cam.cy, cam.distortion[:4])

    def camchain(**block):  # a key given None is left out
        cam0 = {"camera_model": "pinhole", "intrinsics": [cam.fx, cam.fy, cam.cx, cam.cy], "distortion_model": "radtan",
                "distortion_coeffs": list(cam.distortion), "resolution": [cam.width, cam.height],
                "rostopic": "/cam0/image_raw", "T_cam_lidar": T.tolist()}
        return yaml.safe_dump({"cam0": {k: v for k, v in {**cam0, **block}.items() if v is not None}}, default_flow_style=None)

    path = tmp_path / "camchain.yaml"
    path.write_text(camchain())
    assert read_camera(path) == cam
    np.testing.assert_allclose(read_pose(path)[0], T, atol=1e-12)
    path.write_text(camchain(distortion_model="none", distortion_coeffs=[0.0] * 4))
    assert read_camera(path) == without_distortion(cam)
    for text, needle in ((camchain(camera_model="omni"), "camera_model 'omni'"),
                         (camchain(distortion_model="equidistant"), "distortion_model 'equidistant'"),
                         (camchain(intrinsics=[500.0, 500.0]), r"intrinsics must be \[fu, fv, pu, pv\].*got \[500.0, 500.0\]"),
                         (camchain(resolution=640), r"resolution \[width, height\], got .* and 640"),
                         (camchain() + "cam1:\n  camera_model: pinhole\n", r"2 cameras \(cam0, cam1\)")):
        path.write_text(text)
        with pytest.raises(InputError, match=needle):
            read_camera(path)
    for text, needle in ((camchain(T_cam_lidar=[[1, 0, 0], [0, 1, 0]]), "3 or 4 rows of 4 finite numbers"),
                         (camchain(T_cam_lidar=(2 * T).tolist()), "not rigid|orthonormal|last row"),
                         (camchain(T_cam_lidar=None), "no 'T_cam_from_scan'")):
        path.write_text(text)
        with pytest.raises(InputError, match=needle):
            read_pose(path)
    if scene.exists():  # without k3 the depth map differs from calib.txt's at the photo's border
        path.write_text(camchain())
        assert (_pjlab3_depth(tmp_path, "--camera", path, "--pose", path) > 0).sum() > 5000


def test_a_matrix_without_its_cols_is_refused_before_opencv_reads_it(tmp_path):
    """cv2 5.0 reads a matrix's data into a buffer of rows x cols before it compares the counts:
    an extrinsic without its `cols` line (the fuzz's) corrupted the heap, and the process aborted
    or segfaulted later, at random (at exit: 134 or 139). The counts are checked first now."""
    path = tmp_path / "extrinsic.yaml"
    path.write_text("%YAML:1.0\nExtrinsicMat: !!opencv-matrix\n  rows: 4\n  dt: d\n  data: " + str(list(range(16))) + "\n")
    code = ("import sys, rgbd_gt.io\n"
            "try:\n    rgbd_gt.io.read_pose(sys.argv[1])\n"
            "except rgbd_gt.errors.InputError as exc:\n    print(exc)\n")
    proc = subprocess.run([sys.executable, "-c", code, str(path)], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, (proc.returncode, proc.stderr)
    assert proc.stdout.strip().endswith("not a readable OpenCV calibration file (a matrix lacks its rows or cols)")


def test_an_opencv_value_that_is_not_utf8_is_named(tmp_path):
    """The fuzz's byte flip in `<image_height>480</image_height>` made a string node of bytes that
    are not UTF-8; the binding raised UnicodeDecodeError (a traceback) when the value was read."""
    path = tmp_path / "camera.xml"
    path.write_bytes(b'<?xml version="1.0"?>\n<opencv_storage>\n<camera_matrix type_id="opencv-matrix">'
                     b"<rows>3</rows><cols>3</cols><dt>d</dt><data>500. 0. 320. 0. 500. 240. 0. 0. 1.</data>"
                     b"</camera_matrix>\n<image_width>640</image_width>\n<image_height>\xd380</image_height>\n"
                     b"</opencv_storage>\n")
    with pytest.raises(InputError, match=r"camera.xml: not a readable OpenCV calibration file \(a value that is not UTF-8 text\)"):
        read_camera(path)


@pytest.mark.parametrize(
    "text,needle",
    [
        ("width: 640\nheight: 480\nfx: 500\n", "lacks fy, cx, cy"),
        ("width: 640\nheight: 480\nfx: 500\nfy: 500\ncx: 320\ncy: 240\ndistortion: [1, 2, 3]\n", "coefficients"),
        ("width: 640\nheight: 480\nfx: -5\nfy: 500\ncx: 320\ncy: 240\n", "fx must lie between 1 and"),
        # fuzz seed 20: a resolution cut to [1, 2] said only "... 1000 x the image size, got 2152.8"
        ("width: 1\nheight: 2\nfx: 2152.8\nfy: 2152.8\ncx: 0.5\ncy: 1\n", r"image size \(1x2: up to 2000\), got 2152.8$"),
        ("width: [640\n", "invalid YAML"),
        # fuzz seed 22: said "fx, fy, cx, cy and distortion must be numbers", naming none
        ("width: 640\nheight: 480\nfx: 500\nfy: 500\ncx: 320\ncy: 240\ndistortion: [0.1, abc, 0, 0]\n",
         r"distortion must be numbers, got 'abc' \(entry 2 of 4\)$"),
        # fuzz seed 31: a bad fifth coefficient was cut off the 80 characters of the list shown
        ("width: 640\nheight: 480\nfx: 500\nfy: 500\ncx: 320\ncy: 240\n"
         "distortion: [-0.10887398992097819, 0.0009386634902923338, 0.00011448253299620886, -0.0002913, abc]\n",
         r"distortion must be numbers, got 'abc' \(entry 5 of 5\)$"),
        # fuzz seed 32: a single number in place of the list said only "got 1"
        ("width: 640\nheight: 480\nfx: 500\nfy: 500\ncx: 320\ncy: 240\ndistortion: .nan\n",
         r"distortion must have 4, 5, 8, 12 or 14 coefficients, got 1 \(nan\)$"),
        ("width: 640\nheight: 480\nfx: 500\nfy: [500]\ncx: 320\ncy: 240\n", r"fy must be a number, got \[500\]$"),
        # a model that turns back 39 deg off the axis, short of the corners (45 deg): they would have no ray
        ("width: 640\nheight: 480\nfx: 400\nfy: 400\ncx: 320\ncy: 240\ndistortion: [-0.6, 0.1, 0, 0]\n",
         r"the lens model turns back inside the 640x480 image .*corners lie at 1\.002\), so its outer pixels have no ray: "
         "coefficients fitted"),
        # fuzz seed 34: a cx of -1 was blamed on the distortion alone
        ("width: 640\nheight: 480\nfx: 530.4\nfy: 530.4\ncx: -1\ncy: 246.07\n"
         "distortion: [-0.10887, 0.00094, 0.00011, -0.00029, 0.0]\n",
         r"no ray: the principal point \(-1, 246.07\) off the image, coefficients fitted"),
        ("- 1\n- 2\n", "mapping"),
        ("%YAML:1.0\ncamera_matrix: !!opencv-matrix\n  rows: 3\n  cols: 3\n  dt: d\n  data: [1, 2, 3]\n",
         r"OpenCV calibration file \(a matrix's data does not hold rows x cols values\)$"),
    ],
)
def test_bad_camera_files(tmp_path, text, needle):
    (tmp_path / "c.yaml").write_text(text)
    with pytest.raises(InputError, match=needle):
        read_camera(tmp_path / "c.yaml")


def test_numbers_with_an_exponent(tmp_path):
    """YAML 1.2 reads 5e2 and 1e-3 as numbers, PyYAML as text: where a number is due (a camera
    file's, a config's) they are taken as numbers (fuzz seed 25: "expected a number, got str
    '1e12'"); text that is no number is still named."""
    from rgbd_gt.align.config import RefineConfig
    from rgbd_gt.config import load_config

    (tmp_path / "c.yaml").write_text("width: 640\nheight: 480\nfx: 5e2\nfy: 5.0E+2\ncx: 320\ncy: 24e1\n")
    cam = read_camera(tmp_path / "c.yaml")
    assert (cam.fx, cam.fy, cam.cy) == (500.0, 500.0, 240.0)
    (tmp_path / "r.yaml").write_text("iterations: 1e2\nverify:\n  edge_ratio_ok: 12e-1\n")
    cfg = load_config(RefineConfig, tmp_path / "r.yaml")
    assert cfg.iterations == 100 and cfg.verify.edge_ratio_ok == 1.2
    (tmp_path / "r.yaml").write_text("verify:\n  edge_ratio_ok: 1e\n")
    with pytest.raises(InputError, match=r"r.yaml: verify.edge_ratio_ok: expected a number, got str '1e'$"):
        load_config(RefineConfig, tmp_path / "r.yaml")


def test_image_size_must_match():
    check_image_matches(CAM, (480, 640, 3), "p.png", "c.yaml")
    with pytest.raises(InputError, match="image is 800x600 but camera file c.yaml is for 640x480$"):
        check_image_matches(CAM, (600, 800, 3), "p.png", "c.yaml")
    with pytest.raises(InputError, match="is for 640x480 \\(turned by 90 deg"):
        check_image_matches(CAM, (640, 480, 3), "p.png", "c.yaml")


def test_a_photo_is_read_turned_as_its_exif_orientation_says(tmp_path):
    """A portrait phone JPEG is stored on its side with EXIF orientation 6 (turn 90 deg clockwise):
    read as viewers and OpenCV's imread show it, so an OpenCV calibration of it fits."""
    from PIL import Image

    from rgbd_gt.io.image import read_image

    stored = np.zeros((40, 60, 3), np.uint8)
    stored[:10, :10] = (255, 0, 0)  # red in the stored top-left corner
    im = Image.fromarray(stored)
    exif = im.getexif()
    exif[274] = 6
    im.save(tmp_path / "p.jpg", exif=exif, quality=95)
    photo = read_image(tmp_path / "p.jpg")
    assert photo.shape == (60, 40, 3)
    assert photo[:10, -10:, 0].mean() > 200 and photo[:10, :10, 0].mean() < 50  # turned clockwise: now top right
    im.save(tmp_path / "q.jpg", quality=95)  # no orientation: as stored
    assert read_image(tmp_path / "q.jpg").shape == (40, 60, 3)


def test_project_backproject_round_trip():
    rng = np.random.default_rng(0)
    pts = np.stack([rng.uniform(-1, 1, 200), rng.uniform(-0.7, 0.7, 200), rng.uniform(1.5, 4, 200)], 1)
    uv, z = project(CAM, pts)
    np.testing.assert_allclose(z, pts[:, 2])
    np.testing.assert_allclose(backproject(CAM, uv, z), pts, atol=1e-9)
    # distortion moves points compared with the pure pinhole
    uv0, _ = project(without_distortion(CAM), pts)
    assert np.abs(uv - uv0).max() > 5
    assert np.isnan(project(CAM, np.array([[0.0, 0.0, -1.0]]))[0]).all()


def test_undistorted_image_follows_the_pinhole_model():
    """A dot at the distorted projection of a point lands at the pinhole projection after undistortion."""
    import cv2

    pt = np.array([[0.42, -0.3, 1.0]])
    (ud, vd), = project(CAM, pt)[0]
    img = np.zeros((480, 640), np.float32)
    cv2.circle(img, (int(round(ud * 16)), int(round(vd * 16))), 4 * 16, 1.0, -1, shift=4)
    und = undistort_image(CAM, img)
    ys, xs = np.nonzero(und > 0.5)
    (u0, v0), = project(without_distortion(CAM), pt)[0]
    assert abs(xs.mean() - u0) < 0.3 and abs(ys.mean() - v0) < 0.3


def test_rescale_keeps_pixel_centres():
    half = rescale(CAM, 320, 240)
    assert (half.fx, half.fy) == (CAM.fx / 2, CAM.fy / 2)
    pt = np.array([[0.3, 0.2, 2.0]])
    uv_full = project(without_distortion(CAM), pt)[0]
    uv_half = project(without_distortion(half), pt)[0]
    np.testing.assert_allclose((uv_full + 0.5) / 2 - 0.5, uv_half)


@pytest.mark.parametrize("coefficients", [(-0.12, 0.16, 7e-4, 1.4e-3), (-0.10, -0.04, 6e-4, -4e-3, 0.43),
                                          (-0.1, 0.05, 1e-3, -2e-3, 0.02, 0.01, 3e-3, 1e-3),
                                          (-0.1, 0.05, 1e-3, -2e-3, 0.02, 0.01, 3e-3, 1e-3, 1e-3, -2e-3, 3e-3, 5e-4),
                                          (-0.1, 0.05, 1e-3, -2e-3, 0.02, 0.01, 3e-3, 1e-3, 1e-3, -2e-3, 3e-3, 5e-4, 0.01, -0.02)])
def test_distort_is_opencvs_model(coefficients):
    import cv2

    from rgbd_gt.camera import distort

    camera = Camera(1920, 1200, 2150.0, 2155.0, 971.3, 605.9, coefficients)
    xn = np.random.default_rng(1).uniform(-0.6, 0.6, (5000, 2))
    expected = cv2.projectPoints(np.c_[xn, np.ones(len(xn))], np.zeros(3), np.zeros(3), camera.K,
                                 np.array(coefficients))[0].reshape(-1, 2)
    np.testing.assert_allclose(distort(camera, xn), expected, atol=1e-6)


def test_points_beyond_the_lens_fold_are_not_imaged():
    """KITTI's raw camera 2 (2011_09_26: a barrel lens, its coefficients fitted inside the photo):
    the radial model turns back 50 deg off the axis (normalised radius 1.21), so that points 53-58
    deg off the axis would land inside the photo again, ghosts in a sweep's depth map. They are
    not imaged; within the fold the projection is OpenCV's."""
    import cv2

    from rgbd_gt.camera import fold_radius, lens_reach
    from rgbd_gt.scan import Scan
    from rgbd_gt.render.points import seen_points

    cam = Camera(1392, 512, 959.791, 956.9251, 696.0217, 224.1806,
                 (-0.3691481, 0.1968681, 1.353473e-3, 5.677587e-4, -6.770705e-2))
    assert 1.20 < fold_radius(cam.distortion) < 1.22
    assert lens_reach(cam)[1] < lens_reach(cam)[0] < 0.82  # it reaches past the photo's corners, just
    assert fold_radius(()) == fold_radius((0.0, 0.0, 1e-3, 1e-3)) == fold_radius((-0.10, -0.04, 6e-4, -4e-3, 0.43)) == np.inf
    assert 1.65 < fold_radius(CAM.distortion) < 1.75  # far beyond its photo's corners (0.77)
    az = np.radians(np.arange(-89.5, 90, 0.25))
    ring = np.c_[10 * np.sin(az), np.full_like(az, 0.5), 10 * np.cos(az)]  # a ring of returns 10 m round the camera
    uv, z = project(cam, ring)
    r = np.abs(np.tan(az))
    within = r < fold_radius(cam.distortion)
    assert np.isnan(uv[~within]).all() and np.isfinite(uv[within]).all()
    expected = cv2.projectPoints(ring[within], np.zeros(3), np.zeros(3), cam.K, np.array(cam.distortion))[0].reshape(-1, 2)
    np.testing.assert_allclose(uv[within], expected, atol=1e-6)
    idx, _, _ = seen_points(Scan(xyz=ring), cam, np.eye(4))
    assert len(idx) > 50 and r[idx].max() < 0.95  # the photo's edge: 0.93; the ghosts lay at 1.4-1.8

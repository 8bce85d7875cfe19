"""ROS 2 recordings in MCAP (data/recording.py): written with the MCAP project's writer, read back with its
reader; frames equal to what was written (depth to its millimetre steps), the other encodings a camera
driver publishes, and refusals that name the file, the topic and the fix."""

from __future__ import annotations

import io
import json
import subprocess
import sys

import numpy as np
import pytest

from apose_studio.data.dataset import DatasetError, Frame
from apose_studio.data.recording import IMAGE, is_recording, open_recording, write_recording
from apose_studio.geometry import se3
from apose_studio.geometry.camera import CameraIntrinsics
from tests.conftest import SAMPLES

GEARBOX = SAMPLES / "helical_gearbox" / "assembly.yaml"


def _frames(n=3, w=64, h=48):
    rng = np.random.default_rng(0)
    cam = CameraIntrinsics(w, h, 60.0, 61.0, 31.5, 23.5)
    out = []
    for k in range(n):
        depth = rng.uniform(0.3, 1.2, (h, w)).astype(np.float32)
        depth[0, :5] = 0.0  # no reading
        T = se3.make_T(se3.axis_angle_matrix(np.array([0.0, 0.0, 1.0]), 0.1 * k), np.array([0.01 * k, 0.0, 0.5]))
        out.append(Frame(rgb=rng.integers(0, 255, (h, w, 3), dtype=np.uint8), depth=depth, camera=cam, T_world_camera=T))
    return out


def test_a_written_recording_reads_back_frame_for_frame(tmp_path):
    frames = _frames()
    path = write_recording(tmp_path / "rec.mcap", frames, rate_hz=10)
    assert is_recording(path)
    rec = open_recording(path)
    assert len(rec) == 3 and rec.unpaired == 0 and rec.seconds == pytest.approx(0.2)
    assert rec.camera == frames[0].camera
    for k, fr in enumerate(frames):
        got = rec.frame(k)
        assert np.array_equal(got.rgb, fr.rgb)
        assert np.abs(got.depth - fr.depth).max() <= 0.0005 + 1e-6  # 16UC1: millimetre steps
        assert got.depth[0, 0] == 0.0
        np.testing.assert_allclose(got.T_world_camera, fr.T_world_camera, atol=1e-12)
    with pytest.raises(DatasetError, match="frame 3 does not exist"):
        rec.frame(3)


def _custom(path, images: list[tuple[str, str, bytes, int, int, int]], info: bool = True):
    """An MCAP file with the given (topic, encoding, data, width, height, step) images and a CameraInfo."""
    from mcap_ros2.writer import Writer

    from apose_studio.data.recording import CAMERA_INFO

    buf = io.BytesIO()
    w = Writer(buf)
    image = w.register_msgdef("sensor_msgs/msg/Image", IMAGE)
    cinfo = w.register_msgdef("sensor_msgs/msg/CameraInfo", CAMERA_INFO)
    t = 10 ** 18
    head = {"stamp": {"sec": 0, "nanosec": 0}, "frame_id": "cam"}
    for topic, enc, data, wd, h, step in images:
        w.write_message(topic, image, {"header": head, "height": h, "width": wd, "encoding": enc, "is_bigendian": 0,
                                       "step": step, "data": data}, log_time=t, publish_time=t)
    if info:
        w.write_message("/cam/color/camera_info", cinfo, {
            "header": head, "height": 2, "width": 3, "distortion_model": "", "d": [], "k": [5.0, 0, 1.0, 0, 5.0, 0.5, 0, 0, 1],
            "r": [0.0] * 9, "p": [0.0] * 12, "binning_x": 0, "binning_y": 0,
            "roi": {"x_offset": 0, "y_offset": 0, "height": 0, "width": 0, "do_rectify": False}}, log_time=t, publish_time=t)
    w.finish()
    path.write_bytes(buf.getvalue())
    return path


def test_bgr_colour_and_float_depth_in_metres(tmp_path):
    bgr = np.arange(2 * 3 * 3, dtype=np.uint8).reshape(2, 3, 3)
    depth = np.array([[0.5, np.nan, 1.25], [-1.0, 2.0, 0.75]], "<f4")
    path = _custom(tmp_path / "r.mcap", [("/cam/color/image_raw", "bgr8", bgr.tobytes(), 3, 2, 9),
                                         ("/cam/depth/image_raw", "32FC1", depth.tobytes(), 3, 2, 12)])
    fr = open_recording(path).frame(0)
    assert np.array_equal(fr.rgb, bgr[..., ::-1])
    np.testing.assert_array_equal(fr.depth, np.array([[0.5, 0.0, 1.25], [0.0, 2.0, 0.75]], np.float32))
    assert fr.camera == CameraIntrinsics(3, 2, 5.0, 5.0, 1.0, 0.5)
    assert np.array_equal(fr.T_world_camera, np.eye(4))  # no pose topic: the camera's own frame


def test_recordings_that_cannot_be_read_say_why(tmp_path):
    rgb = bytes(18)
    only_colour = _custom(tmp_path / "a.mcap", [("/cam/color/image_raw", "rgb8", rgb, 3, 2, 9)])
    with pytest.raises(DatasetError, match=r"no depth image topic .*image_raw \(color\)"):
        open_recording(only_colour)
    no_info = _custom(tmp_path / "b.mcap", [("/cam/color/image_raw", "rgb8", rgb, 3, 2, 9),
                                            ("/cam/depth/image_raw", "16UC1", bytes(12), 3, 2, 6)], info=False)
    with pytest.raises(DatasetError, match="CameraInfo"):
        open_recording(no_info)
    short = _custom(tmp_path / "c.mcap", [("/cam/color/image_raw", "rgb8", bytes(5), 3, 2, 9),
                                          ("/cam/depth/image_raw", "16UC1", bytes(12), 3, 2, 6)])
    with pytest.raises(DatasetError, match="damaged message"):
        open_recording(short).frame(0)
    odd = _custom(tmp_path / "d.mcap", [("/cam/color/image_raw", "rgb8", rgb, 3, 2, 9),
                                        ("/cam/depth/image_raw", "yuv422", bytes(12), 3, 2, 6)])
    with pytest.raises(DatasetError, match="no depth image topic"):
        open_recording(odd)
    (tmp_path / "junk.mcap").write_bytes(b"not an mcap file at all")
    with pytest.raises(DatasetError, match="junk.mcap"):
        open_recording(tmp_path / "junk.mcap")
    bag = tmp_path / "bag"
    bag.mkdir()
    (bag / "metadata.yaml").write_text("rosbag2_bagfile_information: {}\n")
    (bag / "bag_0.db3").write_bytes(b"")
    with pytest.raises(DatasetError, match="ros2 bag convert"):
        open_recording(bag)


def test_a_rosbag2_folder_is_read_through_its_mcap(tmp_path):
    bag = tmp_path / "bag"
    bag.mkdir()
    (bag / "metadata.yaml").write_text("rosbag2_bagfile_information: {storage_identifier: mcap}\n")
    write_recording(bag / "bag_0.mcap", _frames(2))
    assert is_recording(bag) and len(open_recording(bag)) == 2


def test_track_a_recording_exported_from_a_rendered_trajectory(tmp_path):
    """`apose export-mcap` then `apose track REC.mcap --assembly A --step K`, as the README gives them; the
    recorded poses checked against the renderer's truth (the dataset beside it)."""
    from apose_studio.data.dataset import Dataset
    from apose_studio.estimation import truth_box
    from tests.conftest import mssd_to_truth

    run = [sys.executable, "-m", "apose_studio.cli"]
    ds = tmp_path / "ds"
    subprocess.run(run + ["render", str(GEARBOX), "--out", str(ds), "--frames", "4", "--trajectory", "--steps", "2",
                          "--noise", "realsense", "-q"], check=True, capture_output=True)
    rec = tmp_path / "rec.mcap"
    p = subprocess.run(run + ["export-mcap", str(ds), "--step", "2", "--out", str(rec), "--rate", "5"],
                       capture_output=True, text=True)
    assert p.returncode == 0, p.stderr
    out = tmp_path / "t.json"
    truth = Dataset(ds)
    box = ",".join(map(str, truth_box(truth.frame(2, 0).base_mask())))  # the user's box on the first frame
    p = subprocess.run(run + ["track", str(rec), "--assembly", str(GEARBOX), "--step", "2", "--box", box, "--json", str(out)],
                       capture_output=True, text=True)
    assert p.returncode == 0, p.stderr
    doc = json.loads(out.read_text())
    assert [f["mode"] for f in doc["frames"]] == ["detected", "tracked", "tracked", "tracked"]
    for f in doc["frames"]:
        err = mssd_to_truth(f["T_world_part"], truth.frame(2, f["im_id"]).T_world_part, GEARBOX, "wheel")
        assert f["confident"] and err < 0.005, (f["im_id"], err)
    p = subprocess.run(run + ["track", str(rec), "--step", "2"], capture_output=True, text=True)
    assert p.returncode == 2 and "--assembly" in p.stderr and "Traceback" not in p.stderr


def test_neighbours_of_a_bad_recording_are_refused_by_name(tmp_path):
    """A FIFO named .mcap, an image claiming 100000 px a side, a CameraInfo with NaN in K: each a one-line reason."""
    import os

    fifo = tmp_path / "live.mcap"
    os.mkfifo(fifo)
    with pytest.raises(DatasetError, match="not a regular file"):
        open_recording(fifo)
    huge = _custom(tmp_path / "h.mcap", [("/cam/color/image_raw", "rgb8", bytes(18), 3, 2, 9),
                                         ("/cam/depth/image_raw", "16UC1", bytes(12), 100000, 2, 6)])
    with pytest.raises(DatasetError, match="100000x2 image"):
        open_recording(huge).frame(0)


def test_an_output_file_beside_the_input_is_checked_as_one_path(tmp_path):
    """check_output_file takes one input path as one path (a string was once read as its characters, so that
    every existing output file was refused as "a file of the input /")."""
    from apose_studio.cli.common import check_output_file
    from apose_studio.errors import AposeError

    (tmp_path / "ds").mkdir()
    (tmp_path / "ds" / "dataset_info.json").write_text("{}")
    (tmp_path / "old.json").write_text("{}")
    check_output_file(tmp_path / "old.json", "--json", str(tmp_path / "ds"))  # an earlier output: replaced
    with pytest.raises(AposeError, match="a file of the input"):
        check_output_file(tmp_path / "ds" / "dataset_info.json", "--json", str(tmp_path / "ds"))


def test_an_image_of_the_wrong_size_and_an_oversized_chunk_are_refused_by_name(tmp_path, monkeypatch):
    """Found by an outside review: one byte more than height x step gave an internal error (a reshape), and a
    35 kB file whose zstd chunk claimed 1 GiB made the studio allocate 4.6 GB before any check."""
    from apose_studio.data import recording

    extra = _custom(tmp_path / "e.mcap", [("/cam/color/image_raw", "rgb8", bytes(19), 3, 2, 9),
                                          ("/cam/depth/image_raw", "16UC1", bytes(12), 3, 2, 6)])
    with pytest.raises(DatasetError, match=r"19 bytes .* damaged message"):
        open_recording(extra).frame(0)
    fine = write_recording(tmp_path / "f.mcap", _frames(2))
    monkeypatch.setattr(recording, "MAX_CHUNK_BYTES", 1000)  # the frames' chunks are ~15 kB
    with pytest.raises(DatasetError, match="a chunk of .* uncompressed; at most"):
        open_recording(fine)

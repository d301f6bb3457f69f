"""ROS 1 / ROS 2 bags as predict inputs (`data.rosbag`): small bags written here with rosbags'
own writers, read back to the same counts, and predicted by topic."""

import os

import numpy as np
import pytest

from irdepth_jax import cli
from irdepth_jax.data.rawio import read_frames

rosbags = pytest.importorskip("rosbags", reason="the rosbag extra (rosbags) is not installed")
from rosbags.rosbag1 import Writer as Writer1  # noqa: E402
from rosbags.rosbag2 import Writer as Writer2  # noqa: E402
from rosbags.typesys import Stores, get_typestore  # noqa: E402

H, W = 32, 48
THERMAL = "/thermal/image_raw"
IMAGE = "sensor_msgs/msg/Image"


def counts(k):
    """Frame k: 14-bit counts that differ per frame and pixel."""
    return (3000 + 37 * k + np.arange(H * W).reshape(H, W) * (k + 3) % 9000).astype(np.uint16)


def image(store, frame, encoding="mono16", big_endian=False, padding=0):
    """A sensor_msgs/Image of `frame` (H, W), each row followed by `padding` bytes."""
    dtype = frame.dtype.newbyteorder(">" if big_endian else "<")
    rows = frame.astype(dtype).view(np.uint8).reshape(H, -1)
    data = np.pad(rows, ((0, 0), (0, padding))).ravel()
    types = store.types
    header = types["std_msgs/msg/Header"]
    seq = {"seq": 0} if "seq" in header.__dataclass_fields__ else {}  # ROS 1's header has one
    header = header(stamp=types["builtin_interfaces/msg/Time"](sec=0, nanosec=0),
                    frame_id="thermal", **seq)
    return types[IMAGE](header=header, height=H, width=W, encoding=encoding,
                        is_bigendian=int(big_endian), step=rows.shape[1] + padding, data=data)


def write_bag(path, topics, ros1=False):
    """A bag at `path` (ROS 1 .bag file or ROS 2 folder): {topic: [Image kwargs]} in order."""
    store = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
    writer = Writer1(path) if ros1 else Writer2(path, version=9)
    with writer:
        for topic, frames in topics.items():
            connection = writer.add_connection(topic, IMAGE, typestore=store)
            for k, kwargs in enumerate(frames):
                msg = image(store, **kwargs)
                data = store.serialize_ros1(msg, IMAGE) if ros1 else store.serialize_cdr(msg, IMAGE)
                writer.write(connection, 1_000_000 * (k + 1), data)
    return path


@pytest.mark.parametrize("ros1", [False, True], ids=["ros2", "ros1"])
def test_bag_frames_read_to_the_same_counts(tmp_path, ros1):
    """mono16 in either byte order and with row padding; the topic named or, when the bag has
    one image topic, found; a wrong topic or two image topics without --topic are refused with
    the image topics listed; mono8 images are read and refused as 8-bit."""
    frames = [counts(k) for k in range(3)]
    bag = write_bag(tmp_path / ("cam.bag" if ros1 else "cam"), {
        THERMAL: [{"frame": frames[0]}, {"frame": frames[1], "big_endian": True},
                  {"frame": frames[2], "padding": 6}]}, ros1)
    read = read_frames(str(bag), 14, THERMAL)
    assert [name for name, _ in read] == ["cam_p0000", "cam_p0001", "cam_p0002"]
    for (_, got), want in zip(read, frames):
        np.testing.assert_array_equal(got, want)
    np.testing.assert_array_equal(read_frames(str(bag), 14)[2][1], frames[2])  # its one topic
    with pytest.raises(ValueError, match=f"{bag}: no topic '/nope' \\(image topics: {THERMAL}\\)"):
        read_frames(str(bag), 14, "/nope")

    two = write_bag(tmp_path / ("two.bag" if ros1 else "two"), {
        THERMAL: [{"frame": frames[0]}],
        "/display/mono8": [{"frame": (frames[0] // 64).astype(np.uint8), "encoding": "mono8"}]},
        ros1)
    with pytest.raises(ValueError, match=f"2 image topics \\(/display/mono8, {THERMAL}\\); "
                                         "name one with --topic"):
        read_frames(str(two), 14)
    with pytest.raises(ValueError, match="8-bit image, not raw thermal counts"):
        read_frames(str(two), 14, "/display/mono8")


def test_predict_a_bag_by_topic(untrained_model, tmp_path, capsys):
    """`irdepth predict BAG --topic T`: one set of outputs per message, named BAG_pNNNN; a ROS
    2 bag folder inside an input folder is read as one input."""
    frames = [counts(k) for k in range(2)]
    folder = tmp_path / "drives"
    write_bag(folder / "run1", {THERMAL: [{"frame": f} for f in frames],
                                "/other": [{"frame": frames[0]}]})
    out = tmp_path / "out"
    code = cli.main(["predict", "--checkpoint", str(untrained_model[0]), "--out", str(out),
                     "--no-progress", "--topic", THERMAL, str(folder)])
    _, err = capsys.readouterr()
    assert code == 0, err
    assert sorted(os.listdir(out)) == [f"run1_p{k:04d}_{kind}.png" for k in range(2)
                                       for kind in ("depth", "depth_color", "hsv", "rgb")]

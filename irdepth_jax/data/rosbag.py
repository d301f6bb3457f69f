"""Thermal frames from ROS 1 bags (``.bag`` files) and ROS 2 bags (folders with a
``metadata.yaml``, sqlite3 or MCAP storage): the ``sensor_msgs/msg/Image`` messages of one topic,
through the optional `rosbags` package (Apache-2.0, pure Python: ``pip install
'irdepth_jax[rosbag]'``).

mono16 / 16UC1 images (either byte order) are raw counts; mono8 / 8UC1 images are read too,
and then refused by the raw frame check as 8-bit (an AGC display image, not counts). Other
encodings (colour, float) and other message types (CompressedImage) are a `BagError`.
"""

from __future__ import annotations

import os

import numpy as np

from irdepth_jax.errors import IrdepthError

IMAGE_TYPE = "sensor_msgs/msg/Image"


class BagError(IrdepthError, ValueError):
    """A bag that cannot be read as thermal frames (one line naming the bag and why)."""


ENCODINGS = {"mono16": np.uint16, "16UC1": np.uint16, "mono8": np.uint8, "8UC1": np.uint8}
"""The image encodings read, and their pixel type."""


def is_bag(path: str) -> bool:
    """Whether `path` is a ROS 1 bag (a ``.bag`` file) or a ROS 2 bag (a folder holding
    ``metadata.yaml``)."""
    if os.path.isdir(path):
        return os.path.isfile(os.path.join(path, "metadata.yaml"))
    return path.lower().endswith(".bag")


def read_bag(path: str, topic: str | None = None) -> list[np.ndarray]:
    """The images of `topic` in the bag at `path`, in the bag's time order.

    Args:
      path: a ROS 1 ``.bag`` file or a ROS 2 bag folder.
      topic: the image topic; None: the bag's one ``sensor_msgs/msg/Image`` topic.
    Returns:
      [(H, W) uint16 or uint8 arrays], one per message.
    Raises:
      BagError (one line naming the bag): rosbags not installed, an unreadable bag, no such
      topic (the image topics are listed), several image topics and no `topic`, or a message
      of another type or encoding.
    """
    try:
        from rosbags.highlevel import AnyReader
        from rosbags.typesys import Stores, get_typestore
    except ImportError:
        raise BagError(f"{path}: reading ROS bags needs the rosbags package: pip install "
                           "'irdepth_jax[rosbag]'") from None
    from pathlib import Path

    try:
        # a ROS 2 bag without message definitions (before Iron) uses the typestore's
        with AnyReader([Path(path)], default_typestore=get_typestore(Stores.ROS2_HUMBLE)) as reader:
            images = sorted({c.topic for c in reader.connections if c.msgtype == IMAGE_TYPE})
            if topic is None:
                if len(images) != 1:
                    listed = ", ".join(images) if images else "none"
                    raise BagError(f"{path}: {len(images)} image topics ({listed}); name "
                                       "one with --topic")
                topic = images[0]
            connections = [c for c in reader.connections if c.topic == topic]
            if not connections:
                raise BagError(f"{path}: no topic {topic!r} (image topics: "
                                   f"{', '.join(images) or 'none'})")
            if any(c.msgtype != IMAGE_TYPE for c in connections):
                raise BagError(f"{path}: topic {topic} holds {connections[0].msgtype}, not "
                                   f"{IMAGE_TYPE} (raw mono16 images)")
            return [_image(path, topic, reader.deserialize(data, c.msgtype))
                    for c, _, data in reader.messages(connections=connections)]
    except BagError:
        raise
    except Exception as err:  # rosbags' own errors (ReaderError, ...), on a corrupt bag
        raise BagError(f"{path}: not a readable ROS bag ({type(err).__name__}: "
                           f"{str(err).splitlines()[0] if str(err) else ''})") from None


def _image(path: str, topic: str, msg) -> np.ndarray:
    """One sensor_msgs/Image as (H, W) pixels (its rows' padding, `step`, left out)."""
    if msg.encoding not in ENCODINGS:
        raise BagError(f"{path}: topic {topic} has {msg.encoding} images; read: "
                           f"{', '.join(ENCODINGS)} (raw counts are mono16)")
    dtype = np.dtype(ENCODINGS[msg.encoding]).newbyteorder(">" if msg.is_bigendian else "<")
    rows = np.frombuffer(np.asarray(msg.data, np.uint8).tobytes(), np.uint8)
    rows = rows[:msg.height * msg.step].reshape(msg.height, msg.step)
    return rows[:, :msg.width * dtype.itemsize].copy().view(dtype).astype(dtype.newbyteorder("="))

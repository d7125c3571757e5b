"""ROS recordings: read ROS 1 / ROS 2 bags, write depth back (docs/design.md section 11).

- :mod:`crfdepth.io.ros.images`: ``sensor_msgs`` Image and CompressedImage to numpy arrays;
- :mod:`crfdepth.io.ros.messages`: ``sensor_msgs`` CameraInfo and PointCloud2 to numpy arrays,
  and a depth map to a ``32FC1`` image (both read fields through :mod:`crfdepth.io.ros.fields`);
- :mod:`crfdepth.io.ros.tf`: the ``/tf_static`` + ``/tf`` transform tree;
- :mod:`crfdepth.io.ros.bag`: an open recording (topics, time stamps, messages) and the
  pairing of images with clouds by time;
- :mod:`crfdepth.io.ros.writer`: the output bag.

Only ``bag`` and ``writer`` need the optional ``rosbags`` package (``pip install
'crfdepth[ros]'``), and only when they are used; importing this package does not.
"""

from crfdepth.io.ros.bag import Pairing, Recording, camera_info_topic, pair_nearest
from crfdepth.io.ros.images import decode_image
from crfdepth.io.ros.messages import CameraModel, camera_from_info, points_from_cloud, stamp_ns
from crfdepth.io.ros.tf import TransformError, TransformTree

__all__ = ["CameraModel", "Pairing", "Recording", "TransformError", "TransformTree", "camera_from_info",
           "camera_info_topic", "decode_image", "pair_nearest", "points_from_cloud", "stamp_ns"]

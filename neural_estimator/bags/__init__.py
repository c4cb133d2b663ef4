"""MCAP bags in the rosbag2 layout: storage only (no rclpy here). The message layout of every stream
is :mod:`neural_estimator.stream.messages`; scoring a recorded run is
:mod:`neural_estimator.evaluation.bag_report` (in bounded memory: :mod:`~neural_estimator.evaluation.bag_scoring`).

- :class:`BagWriter` / :class:`BagReader`: one ``.mcap`` file, written as rosbag2 writes it, read
  back even when the recording was cut short; :func:`open_bag` also opens a rosbag2 directory.
- :func:`bag_to_arrays` / :func:`arrays_to_bag`: a recorded run as arrays keyed by (trajectory,
  step), and sample bags from simulated data; :func:`load_bag_dataset` for the metrics.
"""

from neural_estimator.bags.dataset import RunArrays, arrays_to_bag, bag_to_arrays, load_bag_dataset
from neural_estimator.bags.errors import BagError, BagWarning, MessageError
from neural_estimator.bags.directory import BagDirectory, open_bag
from neural_estimator.bags.reader import BagDamage, BagReader, Connection
from neural_estimator.bags.writer import LATCHED_QOS, STREAM_QOS, BagWriter, Qos

__all__ = [
    "BagDamage",
    "BagDirectory",
    "BagError",
    "BagReader",
    "BagWarning",
    "BagWriter",
    "Connection",
    "LATCHED_QOS",
    "MessageError",
    "Qos",
    "RunArrays",
    "STREAM_QOS",
    "arrays_to_bag",
    "bag_to_arrays",
    "load_bag_dataset",
    "open_bag",
]

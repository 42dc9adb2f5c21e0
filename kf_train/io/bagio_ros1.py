"""
A ROS 1 ``.bag`` read as the rosbag2 reader is: its messages converted to CDR.

Most public datasets are ROS 1 bags. rosbags reads them (``rosbags.rosbag1.Reader``)
and converts each message's ROS 1 serialisation to the CDR bytes of the same message
in the Jazzy typestore (``Typestore.ros1_to_cdr``: the Header's ``seq`` is dropped),
so :class:`kf_train.io.bagio.BagInput` reads a ROS 1 bag with the decoders, checks and
topic rules of a rosbag2 bag, and its values are the same bit for bit. (rosbags'
``AnyReader`` would deserialise every message into objects instead; the reader here
keeps the offsets-based decoding of :mod:`kf_train.io.bagio_layout`.)
"""

from pathlib import Path
from types import SimpleNamespace
from typing import Iterator, Sequence

from kf_train.io.bagio_types import TYPESTORE
from rosbags.rosbag1 import Reader as Ros1Reader
from rosbags.rosbag1 import ReaderError as Ros1ReaderError

ROS1_SUFFIX = '.bag'
__all__ = ['ROS1_SUFFIX', 'Ros1Bag', 'Ros1ReaderError']


class Ros1Bag:
    """A ROS 1 bag with the interface BagInput uses of ``rosbags.rosbag2.Reader``."""

    def __init__(self, path: Path):
        """Prepare to read the ROS 1 bag at ``path``; :meth:`open` opens it."""
        self._reader = Ros1Reader(path)
        self.is_open = False

    def open(self) -> None:  # noqa: A003 - the name rosbags' readers have
        """Open the bag and read its index (rosbags' ReaderError if it is not one)."""
        self._reader.open()
        self.is_open = True

    @property
    def topics(self) -> dict:
        """Return the topics: name -> an object with ``msgtype``."""
        return {name: SimpleNamespace(msgtype=info.msgtype)
                for name, info in self._reader.topics.items()}

    @property
    def connections(self) -> list:
        """Return the bag's connections: each with topic, msgtype, msgcount and id."""
        return self._reader.connections

    def messages(self, connections: Sequence) -> Iterator[tuple]:
        """Yield (connection, record time [ns], CDR bytes) in recorded order."""
        convert = TYPESTORE.ros1_to_cdr
        for connection, record_ns, raw in self._reader.messages(connections):
            yield connection, record_ns, convert(raw, connection.msgtype)

    def close(self) -> None:
        """Close the bag."""
        self._reader.close()
        self.is_open = False

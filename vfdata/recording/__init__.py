"""The VisionForce layout on MCAP (`vfdata.mcap_io`): the layout, its ROS 2 schemas and messages, the
writer, the reader, the derived recording, info and check."""

from vfdata.mcap_io.file import CorruptChunkError
from vfdata.recording.reader import ForceSeries, PoseSeries, Recording, StereoFrame, TopicInfo
from vfdata.recording.writer import McapWriter

__all__ = ["CorruptChunkError", "ForceSeries", "McapWriter", "PoseSeries", "Recording", "StereoFrame", "TopicInfo"]

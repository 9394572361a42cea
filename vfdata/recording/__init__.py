"""The MCAP layer: ROS 2 schemas and CDR, the layout, the writer, the reader, info and check."""

from vfdata.recording.mcapfile import CorruptChunkError
from vfdata.recording.reader import ForceSeries, PoseSeries, Recording, StereoFrame, TopicInfo
from vfdata.recording.writer import McapWriter

__all__ = ["CorruptChunkError", "ForceSeries", "McapWriter", "PoseSeries", "Recording", "StereoFrame", "TopicInfo"]

"""Mission-log ingest: reading ROS 1/ROS 2 logs into frames, topic mapping, decoding, odometry, writing."""

from mapserver.ingest.decode import decode_image
from mapserver.ingest.frames import Frame, PoseSample
from mapserver.ingest.identity import LogIdentity
from mapserver.ingest.odometry import OdometryState, OdometryTrack, integrate_twist
from mapserver.ingest.reader import LOG_SUFFIXES, MissionLog, open_log
from mapserver.ingest.topics import TopicInfo, TopicMapping, map_topics, parse_topics_arg
from mapserver.ingest.writer import OdomSample, write_log

__all__ = [
    "LOG_SUFFIXES",
    "Frame",
    "LogIdentity",
    "MissionLog",
    "OdomSample",
    "OdometryState",
    "OdometryTrack",
    "PoseSample",
    "TopicInfo",
    "TopicMapping",
    "decode_image",
    "integrate_twist",
    "map_topics",
    "open_log",
    "parse_topics_arg",
    "write_log",
]

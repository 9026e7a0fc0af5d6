"""Scan sources: the :class:`Scan` interface and CARMEN log replay."""

from robot_agent.sources.base import Scan, ScanSource
from robot_agent.sources.carmen import LogFormatError, read_log
from robot_agent.sources.carmen_write import write_log
from robot_agent.sources.laserlog import LaserLog

__all__ = ["LaserLog", "LogFormatError", "Scan", "ScanSource", "read_log", "write_log"]

"""Recording: MCAP episode logs and the recorder node."""

from telerig.ir.mcap_log import LogEntry, McapLog, read_log
from telerig.record.recorder import Recorder

__all__ = ["LogEntry", "McapLog", "Recorder", "read_log"]

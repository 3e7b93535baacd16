"""The MCAP episode log now lives in :mod:`telerig.ir.mcap_log` (below devices, which replay it).

This name stays so existing imports of ``telerig.record.mcap_log`` keep working; new code imports
:mod:`telerig.ir.mcap_log`.
"""

from telerig.ir.mcap_log import (
    DEFAULT_CHUNK_SIZE,
    DEFAULT_FLUSH_INTERVAL_S,
    LogEntry,
    McapLog,
    TopicStats,
    iter_raw,
    read_json,
    read_log,
)

__all__ = [
    "DEFAULT_CHUNK_SIZE",
    "DEFAULT_FLUSH_INTERVAL_S",
    "LogEntry",
    "McapLog",
    "TopicStats",
    "iter_raw",
    "read_json",
    "read_log",
]

"""Python `logging` records of the core, forwarded to a node's rclpy logger.

The core modules (e.g. uav_vs.autopilot.session) log through `logging`; in a node their
lines must reach the console with the node's name and /rosout like the node's own.
"""
import logging

from rclpy.impl.rcutils_logger import RcutilsLogger
from rclpy.logging import LoggingSeverity

SEVERITY = {logging.DEBUG: LoggingSeverity.DEBUG, logging.INFO: LoggingSeverity.INFO,
            logging.WARNING: LoggingSeverity.WARN, logging.ERROR: LoggingSeverity.ERROR,
            logging.CRITICAL: LoggingSeverity.FATAL}


def severity_of(level: int) -> LoggingSeverity:
    """The rclpy severity of a logging level (a level between two takes the lower one)."""
    return SEVERITY[max((lv for lv in SEVERITY if lv <= level), default=logging.DEBUG)]


class RosLogHandler(logging.Handler):
    """A logging.Handler writing each record to an rclpy logger at its severity."""

    def __init__(self, ros_logger: RcutilsLogger):
        super().__init__()
        self.ros_logger = ros_logger

    def emit(self, record: logging.LogRecord) -> None:
        severity = severity_of(record.levelno)
        if not self.ros_logger.is_enabled_for(severity):
            return
        try:
            self._log(self.format(record), severity)
        except Exception:   # as logging.Handler does: a failed record never raises
            self.handleError(record)

    def _log(self, text: str, severity: LoggingSeverity) -> None:
        # rclpy binds one severity to each call site: one call per severity
        if severity is LoggingSeverity.DEBUG:
            self.ros_logger.debug(text)
        elif severity is LoggingSeverity.INFO:
            self.ros_logger.info(text)
        elif severity is LoggingSeverity.WARN:
            self.ros_logger.warning(text)
        elif severity is LoggingSeverity.ERROR:
            self.ros_logger.error(text)
        else:
            self.ros_logger.fatal(text)


def forward(name: str, ros_logger: RcutilsLogger) -> RosLogHandler:
    """Send the `name` logger's records (and its children's) to `ros_logger` only.

    Every record is handed over and the rclpy logger's level decides, the one it has at
    that moment: `--log-level debug`, or a level set while the node runs, shows the
    core's debug lines too. Undo with `stop_forwarding`.
    """
    logger = logging.getLogger(name)
    handler = RosLogHandler(ros_logger)
    logger.addHandler(handler)
    logger.setLevel(logging.DEBUG)
    logger.propagate = False
    return handler


def stop_forwarding(name: str, handler: RosLogHandler) -> None:
    logger = logging.getLogger(name)
    logger.removeHandler(handler)
    logger.propagate = True

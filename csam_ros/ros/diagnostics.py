"""One node's status as a ``diagnostic_msgs/DiagnosticArray`` (``/csam/status``)."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from builtin_interfaces.msg import Time
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue


def node_status(
    name: str, robot: str, ok: bool, message: str, values: Mapping[str, Any], stamp: Time
) -> DiagnosticArray:
    """The status ``name`` of ``robot``'s node: OK or WARN, its message and its values."""
    status = DiagnosticStatus(
        level=DiagnosticStatus.OK if ok else DiagnosticStatus.WARN,
        name=name,
        hardware_id=robot,
        message=message,
        values=[KeyValue(key=k, value=str(v)) for k, v in values.items()],
    )
    array = DiagnosticArray(status=[status])
    array.header.stamp = stamp
    return array

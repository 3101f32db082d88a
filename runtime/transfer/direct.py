"""Direct transfer: the Eq. 8 torque tau* is sent unchanged (the interface's defaults); no model, no settings."""

from __future__ import annotations

from runtime.transfer.interface import TransferScheme
from runtime.transfer.registry import register_scheme

register_scheme("direct", None, lambda context: TransferScheme(), help="Eq. 8 torques alone")

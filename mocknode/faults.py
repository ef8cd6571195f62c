"""Fault injection switches for the mock node (per node, from the scenario or the command line)."""
from __future__ import annotations

from pydantic import BaseModel, ConfigDict, Field


class FaultSpec(BaseModel):
    """Each fault is off by default. Rates are probabilities per byte sent by the node."""

    model_config = ConfigDict(extra="forbid")

    corrupt_byte_rate: float = Field(0.0, ge=0.0, le=1.0, description="flip one random bit of a sent byte")
    drop_byte_rate: float = Field(0.0, ge=0.0, le=1.0, description="silently drop a sent byte")
    stall_probability: float = Field(0.0, ge=0.0, le=1.0, description="per request: do not answer for stall_s")
    stall_s: float = Field(0.0, ge=0.0, description="length of a stall in seconds")
    disconnect_every_s: float = Field(0.0, ge=0.0, description="close the port and open a new one every N s (0=never)")
    reconnect_after_s: float = Field(1.0, ge=0.0, description="how long the port stays gone when disconnected")
    reboot_probability: float = Field(
        0.0, ge=0.0, le=1.0, description="per bulk frame sent: reboot mid-transfer, losing all RAM state"
    )
    garbage_on_power_up: int = Field(0, ge=0, description="bytes of random garbage sent at (re)boot")
    protocol_version: int | None = Field(None, description="announce this protocol version instead of the real one")

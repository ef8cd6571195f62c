"""The numbered requirements of docs/protocol.md that ``pipesentry node-check`` runs, in run order.

Each id is a clause of docs/protocol.md (the document marks it **R-...**); a test keeps the
two lists equal, so a requirement cannot be checked without being written down, or the other
way round.
"""
from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class Requirement:
    id: str
    section: str  # of docs/protocol.md
    text: str


REQUIREMENTS: tuple[Requirement, ...] = (
    Requirement("R-INFO-1", "4", "INFO_REPLY is consistent: frame and chunk size, channels, capabilities, boot id, "
                "versions"),
    Requirement("R-FRAME-1", "2", "reply frames are well formed: REPLY set, no unknown flag, request id echoed, LAST "
                "on the last"),
    Requirement("R-VER-1", "3.1", "INFO is answered whatever its header version, in the newest version both speak"),
    Requirement("R-VER-2", "3.1", "a request in a version the node does not speak: ERROR BAD_VERSION, nothing runs"),
    Requirement("R-REQ-1", "3", "request_id 0: ERROR MALFORMED, nothing runs"),
    Requirement("R-REQ-2", "3", "an unknown msg_type: ERROR UNKNOWN_COMMAND with request_type echoed"),
    Requirement("R-REQ-3", "4", "a payload longer or shorter than its table (chunk lists included): ERROR MALFORMED"),
    Requirement("R-FRAME-2", "2", "a frame with a wrong CRC-32C is dropped silently and counted in crc_errors"),
    Requirement("R-FRAME-3", "2", "a frame under 14 or over 4096 decoded bytes is dropped silently and counted in "
                "framing_errors"),
    Requirement("R-FRAME-4", "2", "garbage and idle fill (00 00) before a frame are skipped and the frame answered"),
    Requirement("R-CONF-1", "4.3", "CONFIGURE applies exactly the settings asked for and echoes them"),
    Requirement("R-CONF-2", "4.3", "CONFIGURE outside the limits: ERROR BAD_ARGUMENT, settings unchanged (never "
                "clamped)"),
    Requirement("R-ACQ-1", "4.4", "ACQUIRE numbers measurements 1, 2, ... per boot and states the settings it was "
                "taken with"),
    Requirement("R-STATUS-1", "4.2", "STATUS agrees with INFO and with the measurements the node holds"),
    Requirement("R-TRACE-1", "5", "READ_TRACES: TRACE_META, then every chunk in order; sizes and transfer CRC right"),
    Requirement("R-TRACE-2", "4.5", "READ_TRACES honours channel masks and sample ranges, refuses ones outside the "
                "record"),
    Requirement("R-BULK-1", "5", "a chunk list is answered with the META and exactly those chunks, ascending, once "
                "each"),
    Requirement("R-CACHE-1", "3.2", "a resent CONFIGURE/ACQUIRE/COMPUTE_DI does not run again; the same id with "
                "another payload does"),
    Requirement("R-CACHE-2", "3.2", "a replay has the original payload, flag CACHED and a CRC over its own header"),
    Requirement("R-CACHE-3", "3.2", "ERROR replies are not cached: a refused request sent again is decided again"),
    Requirement("R-DI-1", "4.6", "COMPUTE_DI/READ_DI: default and requested grids, META agrees, peak is the map's "
                "maximum"),
    Requirement("R-DI-2", "4.6", "the on-board map equals Algorithm 1 on the subsampled traces (units V^2)"),
    Requirement("R-CAP-1", "4.1", "a command of an absent capability gets the documented refusal"),
    Requirement("R-BOOT-1", "3.3", "boot_id is non-zero and the same in every reply of one boot"),
    Requirement("R-BOOT-2", "3.3", "after a power cycle the boot_id is new"),
    Requirement("R-BOOT-3", "3.3", "after a power cycle measurements, maps, baseline and reply cache are gone; ids "
                "restart at 1"),
    Requirement("R-BUSY-1", "3.4", "INFO and STATUS are never BUSY; BUSY runs nothing, is not cached, and ends"),
)

BY_ID = {r.id: r for r in REQUIREMENTS}

"""Run every requirement against the node at a URL, in order, one outcome each."""
from __future__ import annotations

import shlex
import subprocess
from collections.abc import Callable

from nodecheck import checks_commands as commands
from nodecheck import checks_lifecycle as lifecycle
from nodecheck import checks_link as link
from nodecheck import checks_onboard as onboard
from nodecheck.context import Context, describe
from nodecheck.outcomes import Failure, NotApplicable, Outcome, Status
from nodecheck.requirements import REQUIREMENTS
from nodecheck.session import CheckAborted, Session, Timing
from protocol.messages import InfoReply, InfoRequest, MessageError
from protocol.versions import HELLO_VERSION, OLDEST_VERSION, PROTOCOL_VERSION, SUPPORTED_VERSIONS

Check = Callable[[Context], object]

CHECKS: dict[str, Check] = {
    "R-INFO-1": link.check_info,
    "R-FRAME-1": link.check_frames,
    "R-VER-1": link.check_info_any_version,
    "R-VER-2": link.check_bad_version,
    "R-REQ-1": link.check_request_id_zero,
    "R-REQ-2": link.check_unknown_command,
    "R-REQ-3": link.check_lengths,
    "R-FRAME-2": link.check_corrupt_frame,
    "R-FRAME-3": link.check_frame_sizes,
    "R-FRAME-4": link.check_resync,
    "R-CONF-1": commands.check_configure,
    "R-CONF-2": commands.check_configure_limits,
    "R-ACQ-1": commands.check_acquire,
    "R-STATUS-1": commands.check_status,
    "R-TRACE-1": commands.check_traces,
    "R-TRACE-2": commands.check_trace_ranges,
    "R-BULK-1": commands.check_chunk_lists,
    "R-CACHE-1": commands.check_cache_runs_once,
    "R-CACHE-2": commands.check_cache_replay,
    "R-CACHE-3": commands.check_errors_not_cached,
    "R-DI-1": onboard.check_di,
    "R-DI-2": onboard.check_di_values,
    "R-CAP-1": onboard.check_absent_capabilities,
    "R-BOOT-1": lifecycle.check_boot_id,
    "R-BOOT-2": lifecycle.check_new_boot_id,
    "R-BOOT-3": lifecycle.check_ram_cleared,
    "R-BUSY-1": lifecycle.check_busy,
}


def _hello(ctx: Context) -> None:
    """INFO first: the node's identity and the version to speak; CheckAborted if it cannot be had."""
    session = ctx.session
    reply = session.command(InfoRequest(OLDEST_VERSION, PROTOCOL_VERSION), version=HELLO_VERSION)
    if not reply.frames:
        raise CheckAborted(f"no answer to INFO from {session.url}: {describe(reply, session.timing.timeout_s)}")
    frame = reply.frames[0]
    if frame.version not in SUPPORTED_VERSIONS:
        try:
            announced = InfoReply.announced_version(frame.payload)
        except MessageError:
            announced = frame.version
        raise CheckAborted(f"the node speaks protocol version {announced}; node-check speaks "
                           f"{OLDEST_VERSION}..{PROTOCOL_VERSION}")
    ctx.notes["info_evidence"] = reply.evidence()
    ctx.notes["info_frame_version"] = frame.version
    if not isinstance(reply.first, InfoReply):
        raise Failure(f"INFO: {describe(reply, session.timing.timeout_s)}", reply.evidence())
    ctx.info = reply.first
    session.version = frame.version


def run_checks(
    url: str, timing: Timing | None = None, *, reboot: Callable[[], None] | None = None, reboot_wait_s: float = 30.0,
    baudrate: int = 230400, seed: int | None = None,
) -> list[Outcome]:
    """Every requirement's outcome for the node at ``url`` (any pyserial URL). Raises PortVanished
    if the port cannot be opened or vanishes, CheckAborted if the node does not answer INFO."""
    session = Session(url, timing or Timing(), baudrate=baudrate, seed=seed)
    try:
        ctx = Context(session, reboot=reboot, reboot_wait_s=reboot_wait_s)
        try:
            _hello(ctx)
        except Failure as failure:
            first = Outcome(REQUIREMENTS[0], Status.FAILED, failure.detail, failure.evidence)
            rest = [Outcome(r, Status.FAILED, "not checked: no valid INFO_REPLY") for r in REQUIREMENTS[1:]]
            return [first, *rest]
        return [_run(ctx, requirement.id) for requirement in REQUIREMENTS]
    finally:
        session.close()


def _run(ctx: Context, requirement_id: str) -> Outcome:
    requirement = next(r for r in REQUIREMENTS if r.id == requirement_id)
    try:
        result = CHECKS[requirement_id](ctx)
    except Failure as failure:
        return Outcome(requirement, Status.FAILED, failure.detail, failure.evidence)
    if isinstance(result, NotApplicable):
        return Outcome(requirement, Status.NOT_APPLICABLE, result.reason)
    return Outcome(requirement, Status.PASSED, result if isinstance(result, str) else "")


def reboot_by_command(command: str, timeout_s: float = 60.0) -> Callable[[], None]:
    """A reboot hook that runs ``command`` (split like a shell would, not run by one), e.g. a USB
    hub's or a lab power supply's command line; a failing command fails R-BOOT-2 with its output."""
    args = shlex.split(command)
    if not args:
        raise ValueError("the reboot command is empty")

    def reboot() -> None:
        try:
            done = subprocess.run(args, capture_output=True, text=True, timeout=timeout_s, check=False)
        except (OSError, subprocess.TimeoutExpired) as exc:
            raise Failure(f"the reboot command {command!r} could not run: {exc}") from exc
        if done.returncode != 0:
            output = (done.stderr or done.stdout).strip().splitlines()
            raise Failure(f"the reboot command {command!r} exited {done.returncode}: {output[-1] if output else ''}")

    return reboot

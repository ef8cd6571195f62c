"""Checks of a node's life across boots and while it works: R-BOOT-*, R-BUSY-1."""
from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass

from nodecheck.context import Context, describe
from nodecheck.outcomes import Failure, NotApplicable, expect
from protocol.framing import FLAG_CACHED, Frame
from protocol.messages import (
    CAP_ON_BOARD_DI,
    AcquireReply,
    AcquireRequest,
    ErrorCode,
    InfoReply,
    InfoRequest,
    MsgType,
    ReadDiRequest,
    ReadTracesRequest,
    StatusReply,
    StatusRequest,
)
from protocol.versions import PROTOCOL_VERSION

BUSY_AVERAGING = 50  # an acquisition long enough (0.5 s at 10 ms a shot) to send other requests into


def check_boot_id(ctx: Context) -> str:
    seen = ctx.session.boot_ids
    ids = set().union(*seen.values()) if seen else set()
    expect(ids == {ctx.node.boot_id} and ctx.node.boot_id != 0,
           "boot ids seen: " + ", ".join(f"{name} {sorted(v)}" for name, v in sorted(seen.items())))
    return f"0x{ctx.node.boot_id:08X} in {', '.join(sorted(seen))}"


@dataclass(frozen=True)
class PowerCycle:
    boot_id_before: int
    status_after: StatusReply
    measurement_before: int
    cached_acquire: Frame | None
    di_before: int | None


def _power_cycle(ctx: Context) -> PowerCycle:
    assert ctx.reboot is not None
    ctx.configure()
    measurement = ctx.acquire().measurement_id
    di = None
    board = ctx.notes.get("di")
    if board is not None:
        di = board.reply.di_id  # type: ignore[attr-defined]
    before = ctx.status()
    ctx.reboot()
    deadline = time.monotonic() + ctx.reboot_wait_s
    while time.monotonic() < deadline:
        reply = ctx.ask(StatusRequest())
        status = reply.first
        if isinstance(status, StatusReply) and (
            status.boot_id != before.boot_id or status.n_measurements < before.n_measurements
            or status.uptime_s < before.uptime_s
        ):
            frame = ctx.notes.get("cached_acquire")
            return PowerCycle(before.boot_id, status, measurement, frame if isinstance(frame, Frame) else None, di)
        time.sleep(min(0.2, ctx.timeout_s))
    raise Failure(f"no sign of a reboot within {ctx.reboot_wait_s:g} s of the reboot command (STATUS unchanged)")


def check_new_boot_id(ctx: Context) -> NotApplicable | str:
    if ctx.reboot is None:
        return NotApplicable("not exercised: give --reboot-command to power-cycle the node")
    cycle = _power_cycle(ctx)
    ctx.notes["power_cycle"] = cycle
    new = cycle.status_after.boot_id
    expect(new not in (0, cycle.boot_id_before), f"boot_id 0x{new:08X} after the power cycle "
           f"(0x{cycle.boot_id_before:08X} before)")
    info = ctx.expect_message(ctx.session.command(InfoRequest(1, PROTOCOL_VERSION), version=1), InfoReply,
                              "INFO after the power cycle")
    expect(info.boot_id == new, f"INFO boot_id 0x{info.boot_id:08X}, STATUS 0x{new:08X}")
    ctx.info = dataclasses.replace(ctx.node, boot_id=new)
    return f"0x{cycle.boot_id_before:08X} -> 0x{new:08X}"


def check_ram_cleared(ctx: Context) -> NotApplicable | None:
    if ctx.reboot is None:
        return NotApplicable("not exercised: give --reboot-command to power-cycle the node")
    cycle = ctx.notes.get("power_cycle")
    expect(isinstance(cycle, PowerCycle), "the power cycle was not seen (R-BOOT-2)")
    assert isinstance(cycle, PowerCycle)
    status = cycle.status_after
    expect(status.n_measurements == 0 and status.baseline_id == 0,
           f"after the power cycle STATUS holds {status.n_measurements} measurements, baseline {status.baseline_id}")
    ctx.expect_error(ctx.ask(ReadTracesRequest(cycle.measurement_before, ctx.all_channels, 0, 1)),
                     ErrorCode.NO_SUCH_MEASUREMENT, f"READ_TRACES of measurement {cycle.measurement_before} of the "
                     "last boot")
    if cycle.di_before is not None and ctx.has(CAP_ON_BOARD_DI):
        ctx.expect_error(ctx.ask(ReadDiRequest(cycle.di_before)), ErrorCode.NO_SUCH_DI,
                         f"READ_DI of map {cycle.di_before} of the last boot")
    if cycle.cached_acquire is not None:
        resend = dataclasses.replace(cycle.cached_acquire, seq=(cycle.cached_acquire.seq + 1) & 0xFFFF)
        reply = ctx.session.exchange(resend, ctx.session.timing.acquire_s(BUSY_AVERAGING))
        acquired = ctx.expect_message(reply, AcquireReply, "an ACQUIRE resent from the last boot")
        expect(not reply.frames[0].flags & FLAG_CACHED and acquired.measurement_id == 1,
               f"an ACQUIRE resent from the last boot came {'from the cache' if reply.frames[0].flags & FLAG_CACHED else ''}"
               f" as measurement {acquired.measurement_id} (ids restart at 1)", reply.evidence())
    return None


def check_busy(ctx: Context) -> str:
    ctx.configure(dataclasses.replace(ctx.settings(), averaging=BUSY_AVERAGING))
    session = ctx.session
    first, second, status = (session.frame(AcquireRequest(0)), session.frame(AcquireRequest(0)),
                             session.frame(StatusRequest()))
    for frame in (first, second, status):
        session.send(frame)
    wait_s = session.timing.acquire_s(BUSY_AVERAGING)
    replies = session.collect({first.request_id, second.request_id, status.request_id}, wait_s)
    acquired = ctx.expect_message(replies[first.request_id], AcquireReply, "the long ACQUIRE")
    during = replies[status.request_id]
    expect(isinstance(during.first, StatusReply), f"STATUS during an acquisition: {describe(during, wait_s)}",
           during.evidence())
    other = replies[second.request_id]
    note = "requests wait behind an acquisition; never BUSY"
    deadline = time.monotonic() + wait_s
    attempts = 0
    while other.error_code() == ErrorCode.BUSY:
        note = "BUSY during an acquisition, served when resent"
        if time.monotonic() > deadline:
            raise Failure(f"an ACQUIRE sent during another is still BUSY after {attempts} resends over {wait_s:.2f} s, "
                          "the other long done", other.evidence())
        attempts += 1
        time.sleep(min(0.05 * 2**attempts, 0.5))
        other = session.exchange(dataclasses.replace(second, seq=(second.seq + attempts) & 0xFFFF), wait_s)
    again = ctx.expect_message(other, AcquireReply, "the ACQUIRE sent during another")
    expect(not other.frames[0].flags & FLAG_CACHED and again.measurement_id == acquired.measurement_id + 1,
           f"the ACQUIRE sent during another became measurement {again.measurement_id} "
           f"{'(CACHED) ' if other.frames[0].flags & FLAG_CACHED else ''}after {acquired.measurement_id}",
           other.evidence())
    never = [(t, s) for t, s, _ in session.busy_log if t in (MsgType.INFO, MsgType.STATUS)]
    unserved = [(t, s) for t, s, served in session.busy_log if not served]
    expect(not never and not unserved, "; ".join(
        [f"msg_type {t:#04x} answered BUSY" for t, _ in never]
        + [f"msg_type {t:#04x} BUSY for {s:.2f} s and never served" for t, s in unserved]))
    return note

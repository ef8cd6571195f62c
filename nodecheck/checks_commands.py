"""Checks of the commands and the reply cache: R-CONF-*, R-ACQ-1, R-STATUS-1, R-TRACE-*, R-BULK-1, R-CACHE-*."""
from __future__ import annotations

import dataclasses
import struct

import numpy as np

from nodecheck.context import CHECK_AVERAGING, Context, describe, same_f32
from nodecheck.outcomes import Failure, NotApplicable, expect
from protocol.bulk import n_chunks_for
from protocol.framing import FLAG_CACHED
from protocol.messages import (
    CAP_BASELINE_SLOT,
    CAP_CHUNK_RETRANSMIT,
    MAX_CHUNK_LIST,
    AcquireReply,
    AcquireRequest,
    ConfigureReply,
    ConfigureRequest,
    ErrorCode,
    MsgType,
    ReadTracesRequest,
    StatusRequest,
    TraceMeta,
)

SETTINGS_FIELDS = ("excitation_hz", "cycles", "averaging", "channel_mask", "n_samples")


def _settings_differ(asked: ConfigureRequest, got: object) -> list[str]:
    out = []
    for name in SETTINGS_FIELDS:
        a, b = getattr(asked, name), getattr(got, name, None)
        if b is None:
            continue  # a version-1 ACQUIRE_REPLY does not state it
        if not (same_f32(a, b) if isinstance(a, float) else a == b):
            out.append(f"{name} {b} (asked {a})")
    return out


def check_configure(ctx: Context) -> str:
    asked = ctx.settings()
    reply = ctx.ask(asked)
    applied = ctx.expect_message(reply, ConfigureReply, "CONFIGURE")
    differ = _settings_differ(asked, applied)
    expect(not differ, "CONFIGURE_REPLY: " + ", ".join(differ), reply.evidence())
    subset = dataclasses.replace(asked, channel_mask=asked.channel_mask & 0b1 | 1 << (ctx.node.n_channels - 1))
    applied = ctx.expect_message(ctx.ask(subset), ConfigureReply, "CONFIGURE of two channels")
    expect(applied.channel_mask == subset.channel_mask, f"channel_mask 0x{applied.channel_mask:X} applied, "
           f"0x{subset.channel_mask:X} asked")
    ctx.configure(asked)
    return f"{asked.n_samples} samples x {ctx.node.n_channels} channels, averaging {asked.averaging}"


def check_configure_limits(ctx: Context) -> None:
    asked = ctx.settings()
    ctx.configure(asked)
    refused = [
        ("n_samples = max_samples + 1", dataclasses.replace(asked, n_samples=ctx.node.max_samples + 1)),
        ("averaging 0", dataclasses.replace(asked, averaging=0)),
        ("cycles 0", dataclasses.replace(asked, cycles=0)),
        ("channel_mask 0", dataclasses.replace(asked, channel_mask=0)),
        ("excitation 500 Hz", dataclasses.replace(asked, excitation_hz=500.0)),
    ]
    if ctx.node.n_channels < 32:
        refused.append(("a channel beyond n_channels", dataclasses.replace(
            asked, channel_mask=asked.channel_mask | 1 << ctx.node.n_channels)))
    failures = []
    for what, request in refused:
        reply = ctx.ask(request)
        first = reply.first
        if reply.error_code() != ErrorCode.BAD_ARGUMENT:
            clamped = isinstance(first, ConfigureReply)
            failures.append(f"{what}: {describe(reply, ctx.timeout_s)}" + (
                f" with {', '.join(_settings_differ(request, first))} (clamped)" if clamped else ""))
            ctx.configure(asked)
    differ = _settings_differ(asked, ctx.acquire())
    if differ:
        failures.append(f"after the refusals the node acquires with {', '.join(differ)}")
    expect(not failures, "; ".join(failures))


def _expect_states(ctx: Context, acquired: AcquireReply, asked: ConfigureRequest, what: str) -> None:
    differ = _settings_differ(asked, acquired)
    if ctx.version >= 2:
        missing = [n for n in ("excitation_hz", "cycles", "averaging", "fs_hz") if getattr(acquired, n) is None]
        differ += [f"{n} missing" for n in missing]
        if acquired.fs_hz is not None and not same_f32(acquired.fs_hz, ctx.node.fs_hz):
            differ.append(f"fs_hz {acquired.fs_hz} (INFO {ctx.node.fs_hz})")
    expect(not differ, f"{what} states {', '.join(differ)}")
    expect(acquired.boot_id == ctx.node.boot_id, f"{what}: boot_id {acquired.boot_id}, INFO {ctx.node.boot_id}")


def check_acquire(ctx: Context) -> str:
    asked = ctx.settings()
    ctx.configure(asked)
    first, second = ctx.acquire(), ctx.acquire()
    expect(second.measurement_id == first.measurement_id + 1,
           f"measurement ids {first.measurement_id} then {second.measurement_id}")
    expect(not first.is_baseline, "ACQUIRE(as_baseline=0) answered is_baseline=1")
    _expect_states(ctx, second, asked, f"ACQUIRE_REPLY of measurement {second.measurement_id}")
    if ctx.has(CAP_BASELINE_SLOT):
        baseline = ctx.acquire(as_baseline=1)
        expect(baseline.is_baseline and baseline.measurement_id == second.measurement_id + 1,
               f"ACQUIRE(as_baseline=1): is_baseline {baseline.is_baseline}, id {baseline.measurement_id}")
        status = ctx.status()
        expect(status.baseline_id == baseline.measurement_id,
               f"STATUS baseline_id {status.baseline_id} after baseline {baseline.measurement_id}")
    return "settings stated" if ctx.version >= 2 else "version 1: channel mask and length stated"


def check_status(ctx: Context) -> None:
    status = ctx.status()
    expect(status.boot_id == ctx.node.boot_id, f"boot_id {status.boot_id}, INFO {ctx.node.boot_id}")
    expect(status.busy == 0, f"busy {status.busy} while idle")
    expect(1 <= status.n_measurements <= ctx.node.max_measurements,
           f"n_measurements {status.n_measurements} after acquisitions (max_measurements {ctx.node.max_measurements})")
    if status.baseline_id:
        reply = ctx.ask(ReadTracesRequest(status.baseline_id, ctx.all_channels, 0, 1))
        meta = ctx.expect_message(reply, TraceMeta, f"READ_TRACES of the baseline {status.baseline_id}")
        expect(meta.is_baseline == 1, f"the baseline {status.baseline_id} reads is_baseline={meta.is_baseline}")


def check_traces(ctx: Context) -> str:
    ctx.configure()
    acquired = ctx.acquire()
    record = ctx.read_record(acquired)
    meta, info = record.meta, ctx.node
    n_channels = acquired.channel_mask.bit_count()
    expected_total = n_channels * acquired.n_samples * 2
    problems = []
    if (meta.measurement_id, meta.boot_id) != (acquired.measurement_id, info.boot_id):
        problems.append(f"META measurement {meta.measurement_id} boot {meta.boot_id}")
    if (meta.start, meta.count, meta.channel_mask) != (0, acquired.n_samples, acquired.channel_mask):
        problems.append(f"META start {meta.start} count {meta.count} mask 0x{meta.channel_mask:X}")
    if meta.total_bytes != expected_total or meta.chunk_bytes != info.chunk_bytes:
        problems.append(f"total_bytes {meta.total_bytes} (expected {expected_total}), chunk_bytes {meta.chunk_bytes}")
    if meta.n_chunks != n_chunks_for(meta.total_bytes, meta.chunk_bytes):
        problems.append(f"n_chunks {meta.n_chunks} for {meta.total_bytes} bytes")
    if not same_f32(meta.fs_hz, info.fs_hz) or meta.adc_bits != info.adc_bits:
        problems.append(f"fs_hz {meta.fs_hz} adc_bits {meta.adc_bits} (INFO {info.fs_hz}, {info.adc_bits})")
    if ctx.version >= 2:
        stated = (meta.excitation_hz, meta.cycles, meta.averaging, meta.record_channel_mask, meta.record_n_samples)
        said = (acquired.excitation_hz, acquired.cycles, acquired.averaging, acquired.channel_mask, acquired.n_samples)
        if stated != said:
            problems.append(f"META settings {stated} != ACQUIRE_REPLY {said}")
    bulk = ctx.read(ReadTracesRequest(acquired.measurement_id, acquired.channel_mask, 0, 0), TraceMeta, "READ_TRACES")
    indices = [c.index for c in bulk.chunks]
    if indices != list(range(meta.n_chunks)):
        problems.append(f"chunks arrived as {indices[:8]}... not 0..{meta.n_chunks - 1} in order")
    for chunk in bulk.chunks:
        want = min(meta.chunk_bytes, meta.total_bytes - chunk.index * meta.chunk_bytes)
        if len(chunk.data) != want or chunk.n_chunks != meta.n_chunks:
            problems.append(f"chunk {chunk.index} has {len(chunk.data)} bytes of {chunk.n_chunks} chunks")
            break
    expect(not problems, "; ".join(problems), bulk.reply.evidence())
    ctx.record = record
    return f"{meta.total_bytes} bytes in {meta.n_chunks} chunks"


def check_trace_ranges(ctx: Context) -> None:
    record = ctx.ensure_record()
    rid, n = record.acquired.measurement_id, record.acquired.n_samples
    channels = [i for i in range(32) if record.acquired.channel_mask >> i & 1]
    pick = sorted({channels[0], channels[-1]})
    mask = sum(1 << c for c in pick)
    start, count = min(100, n // 2), min(50, n - min(100, n // 2))
    sub = ctx.read(ReadTracesRequest(rid, mask, start, count), TraceMeta, "READ_TRACES of two channels")
    want = record.codes[[channels.index(c) for c in pick], start : start + count]
    got = np.frombuffer(sub.data, dtype="<i2")
    expect(got.size == want.size and np.array_equal(got.reshape(want.shape), want),
           f"channels {pick} samples {start}+{count} differ from the same slice of the full read", sub.reply.evidence())
    tail = ctx.read(ReadTracesRequest(rid, mask, n - 10, 0), TraceMeta, "READ_TRACES with count 0")
    expect(isinstance(tail.meta, TraceMeta) and tail.meta.count == 10,
           f"count 0 from sample {n - 10} read {getattr(tail.meta, 'count', None)} samples, not the last 10")
    refused = [("channel_mask 0", ReadTracesRequest(rid, 0, 0, 0), ErrorCode.BAD_ARGUMENT),
               (f"start {n}", ReadTracesRequest(rid, mask, n, 0), ErrorCode.BAD_ARGUMENT),
               (f"samples {n - 5}+6", ReadTracesRequest(rid, mask, n - 5, 6), ErrorCode.BAD_ARGUMENT),
               ("measurement 0xFFFFFFF0", ReadTracesRequest(0xFFFFFFF0, mask, 0, 0), ErrorCode.NO_SUCH_MEASUREMENT)]
    if len(channels) < 32:
        outside = next(i for i in range(32) if not record.acquired.channel_mask >> i & 1)
        refused.append((f"channel {outside}, not in the record", ReadTracesRequest(rid, 1 << outside, 0, 0),
                        ErrorCode.BAD_ARGUMENT))
    for what, request, code in refused:
        ctx.expect_error(ctx.ask(request), code, f"READ_TRACES {what}")


def check_chunk_lists(ctx: Context) -> NotApplicable | None:
    if not ctx.has(CAP_CHUNK_RETRANSMIT):
        return NotApplicable("capability CHUNK_RETRANSMIT absent")
    record = ctx.ensure_record()
    rid, mask = record.acquired.measurement_id, record.acquired.channel_mask
    n_chunks, size = record.meta.n_chunks, record.meta.chunk_bytes
    wanted = (min(2, n_chunks - 1), 0, min(2, n_chunks - 1))  # unsorted, with a duplicate
    bulk = ctx.read(ReadTracesRequest(rid, mask, 0, 0, wanted), TraceMeta, f"READ_TRACES of chunks {wanted}")
    expect(bulk.meta == record.meta, "the META of a chunk re-request differs from the first", bulk.reply.evidence())
    indices = [c.index for c in bulk.chunks]
    shown = indices if len(indices) <= 8 else [*indices[:4], "...", indices[-1]]
    expect(indices == sorted(set(wanted)), f"chunks {wanted} asked, {len(indices)} sent: {shown}",
           bulk.reply.evidence())
    for chunk in bulk.chunks:
        expect(chunk.data == record.data[chunk.index * size : (chunk.index + 1) * size],
               f"chunk {chunk.index} differs from the first read")
    beyond = ctx.ask(ReadTracesRequest(rid, mask, 0, 0, (n_chunks,)))
    ctx.expect_error(beyond, ErrorCode.BAD_ARGUMENT, f"chunk index {n_chunks} of {n_chunks}")
    expect(len(beyond.frames) == 1, "a refused chunk list still sent chunks", beyond.evidence())
    too_many = ReadTracesRequest(rid, mask, 0, 0).encode(ctx.version)[:-2] + struct.pack(
        f"<H{MAX_CHUNK_LIST + 1}H", MAX_CHUNK_LIST + 1, *([0] * (MAX_CHUNK_LIST + 1)))
    ctx.expect_error(ctx.session.command(StatusRequest(), msg_type=MsgType.READ_TRACES, payload=too_many),
                     ErrorCode.MALFORMED, f"a list of {MAX_CHUNK_LIST + 1} chunks")
    return None


def check_cache_runs_once(ctx: Context) -> str:
    ctx.configure()
    frame = ctx.session.frame(AcquireRequest(0))
    wait_s = ctx.session.timing.acquire_s(CHECK_AVERAGING)
    first = ctx.expect_message(ctx.session.exchange(frame, wait_s), AcquireReply, "ACQUIRE")
    ctx.session.exchange(ctx.session.frame(AcquireRequest(0), request_id=frame.request_id), wait_s)
    after = ctx.acquire().measurement_id
    expect(after == first.measurement_id + 1, f"a resent ACQUIRE (id {frame.request_id}) acquired again: the "
           f"next measurement is {after}, not {first.measurement_id + 1}")
    ctx.notes["cached_acquire"] = frame
    if not ctx.has(CAP_BASELINE_SLOT):
        return "the resend answered from the cache"
    other = ctx.session.frame(AcquireRequest(1), request_id=frame.request_id)
    reply = ctx.expect_message(ctx.session.exchange(other, wait_s), AcquireReply, "ACQUIRE(1) with a cached id")
    expect(reply.measurement_id == after + 1 and reply.is_baseline,
           f"the same id with another payload was not run as a new command: measurement {reply.measurement_id}")
    return "the resend answered from the cache; another payload ran"


def check_cache_replay(ctx: Context) -> None:
    frame = ctx.session.frame(ctx.settings())
    original = ctx.session.exchange(frame)
    ctx.expect_message(original, ConfigureReply, "CONFIGURE")
    replay = ctx.session.exchange(ctx.session.frame(ctx.settings(), request_id=frame.request_id))
    if replay.bad_frames:
        raise Failure(f"the replay of CONFIGURE (id {frame.request_id}) is not a valid frame: {replay.bad_frames[0]}",
                      replay.evidence())
    ctx.expect_message(replay, ConfigureReply, "the replay of CONFIGURE")
    a, b = original.frames[0], replay.frames[0]
    expect(not a.flags & FLAG_CACHED and b.flags == a.flags | FLAG_CACHED,
           f"flags 0x{a.flags:02X} then 0x{b.flags:02X}: the replay must add CACHED (0x02) only", replay.evidence())
    expect((b.msg_type, b.payload, b.version) == (a.msg_type, a.payload, a.version),
           "the replay's type, version or payload differs from the original", replay.evidence())


def check_errors_not_cached(ctx: Context) -> None:
    frame = ctx.session.frame(dataclasses.replace(ctx.settings(), averaging=0))
    for attempt in ("first", "resent"):
        reply = ctx.session.exchange(ctx.session.frame(dataclasses.replace(ctx.settings(), averaging=0),
                                                       request_id=frame.request_id))
        ctx.expect_error(reply, ErrorCode.BAD_ARGUMENT, f"CONFIGURE averaging 0 ({attempt})")
        expect(not reply.frames[0].flags & FLAG_CACHED, f"the {attempt} refusal came from the reply cache (CACHED)",
               reply.evidence())


"""The mock node's protocol state machine as docs/protocol.md version 2 specifies it, frame in, frames out."""
from __future__ import annotations

import itertools

import pytest

from mocknode.faults import FaultSpec
from mocknode.node import MockNode
from mocknode.scenario import FirmwareSpec, NodeScenario, PowerUpSpec, default_scenario
from protocol.framing import FLAG_CACHED, FLAG_LAST, FLAG_REPLY, Frame
from protocol.messages import (
    AcquireReply,
    AcquireRequest,
    ComputeDiRequest,
    ConfigureRequest,
    ErrorCode,
    ErrorReply,
    InfoReply,
    InfoRequest,
    Message,
    ReadDiRequest,
    ReadTracesRequest,
    StatusReply,
    StatusRequest,
    TraceMeta,
    decode_message,
)
from protocol.versions import common_version


class FakeClock:
    def __init__(self) -> None:
        self.now_s = 1000.0

    def __call__(self) -> float:
        return self.now_s


def make_node(clock=None, *, faults: dict | None = None, firmware: dict | None = None,
              power_up: dict | None = None, n_samples: int = 600) -> MockNode:
    base = default_scenario(1).nodes[0]
    scenario: NodeScenario = base.model_copy(update={
        "acquisition": base.acquisition.model_copy(update={"n_samples": n_samples}),
        "faults": FaultSpec(**(faults or {})),
        "firmware": FirmwareSpec(**(firmware or {})),
        "power_up": PowerUpSpec(**(power_up or {})),
    })
    return MockNode(scenario, clock=clock or FakeClock())


_ids = itertools.count(100)


def ask(node: MockNode, message: Message, *, version: int = 2, request_id: int | None = None) -> list[Frame]:
    rid = next(_ids) if request_id is None else request_id
    return node.handle(Frame(message.TYPE, rid, message.encode(min(version, 2)), seq=1, version=version))


def answer(frames: list[Frame], version: int = 2) -> Message:
    (frame,) = frames
    return decode_message(frame.msg_type, frame.payload, version)


@pytest.mark.parametrize("host, node, expected", [
    ((1, 2), (1, 2), 2), ((1, 1), (1, 2), 1), ((1, 2), (1, 1), 1), ((2, 5), (1, 3), 3), ((1, 1), (2, 2), None),
])
def test_host_and_node_talk_in_the_newest_version_both_speak(host, node, expected):
    assert common_version(*host, *node) == expected


@pytest.mark.parametrize("header_version", [1, 2, 3, 200])
def test_info_is_answered_whatever_the_header_version_in_the_newest_common_version(header_version):
    node = make_node()
    frames = ask(node, InfoRequest(1, 2), version=header_version)
    assert frames[0].version == 2
    info = answer(frames)
    assert isinstance(info, InfoReply)
    assert (info.protocol_version, info.version_min, info.version_max) == (2, 1, 2)


def test_a_version_1_host_gets_a_version_1_info_reply_from_a_version_2_node():
    frames = ask(make_node(), InfoRequest(1, 1), version=1)
    assert frames[0].version == 1
    info = answer(frames, 1)
    assert info.protocol_version == 1 and info.version_min is None


def test_a_node_sharing_no_version_answers_info_in_its_own_so_the_host_can_say_which():
    frames = ask(make_node(faults={"protocol_version": 3}), InfoRequest(1, 2), version=1)
    assert frames[0].version == 3
    assert InfoReply.announced_version(frames[0].payload) == 3


def test_a_request_in_a_version_the_node_does_not_speak_is_bad_version_in_the_nodes_version():
    node = make_node()
    frames = ask(node, StatusRequest(), version=7)
    assert frames[0].version == 2
    error = answer(frames)
    assert isinstance(error, ErrorReply) and error.code == ErrorCode.BAD_VERSION


def test_a_version_1_node_refuses_other_header_versions_even_for_info():
    node = make_node(faults={"protocol_version": 1})
    error = answer(ask(node, InfoRequest(1, 2), version=2), 1)
    assert isinstance(error, ErrorReply) and error.code == ErrorCode.BAD_VERSION
    info = answer(ask(node, InfoRequest(1, 2), version=1), 1)
    assert isinstance(info, InfoReply) and info.protocol_version == 1


def test_every_request_is_answered_in_the_version_of_its_header():
    node = make_node()
    v1 = ask(node, AcquireRequest(0), version=1)
    v2 = ask(node, AcquireRequest(0), version=2)
    assert (v1[0].version, len(v1[0].payload)) == (1, 25)
    assert (v2[0].version, len(v2[0].payload)) == (2, 36)


def test_request_id_zero_is_malformed_and_runs_nothing():
    node = make_node()
    error = answer(ask(node, AcquireRequest(0), request_id=0))
    assert isinstance(error, ErrorReply) and error.code == ErrorCode.MALFORMED
    assert answer(ask(node, StatusRequest())).n_measurements == 0


def test_the_acquire_reply_and_trace_meta_state_the_settings_the_record_was_taken_with():
    node = make_node()
    ask(node, ConfigureRequest(75e3, 4, 3, 0b1010, 500))
    acquired = answer(ask(node, AcquireRequest(0)))
    assert (acquired.excitation_hz, acquired.cycles, acquired.averaging, acquired.channel_mask,
            acquired.n_samples, acquired.fs_hz) == (75e3, 4, 3, 0b1010, 500, 10e6)
    frames = ask(node, ReadTracesRequest(acquired.measurement_id, 0b10, 100, 50))
    meta = decode_message(frames[0].msg_type, frames[0].payload)
    assert isinstance(meta, TraceMeta)
    assert (meta.channel_mask, meta.count, meta.record_channel_mask, meta.record_n_samples) == (0b10, 50, 0b1010, 500)
    assert (meta.excitation_hz, meta.cycles, meta.averaging) == (75e3, 4, 3)


def test_a_reboot_brings_back_the_power_up_settings_not_the_configured_ones():
    node = make_node(power_up={"averaging": 1, "n_samples": 500, "excitation_hz": 60e3})
    assert answer(ask(node, AcquireRequest(0))).averaging == 1
    ask(node, ConfigureRequest(85e3, 5, 10, 0xFFFF, 600))
    assert answer(ask(node, AcquireRequest(0))).averaging == 10
    boot_id = node.boot_id
    node.boot()
    after = answer(ask(node, AcquireRequest(0)))
    assert (after.averaging, after.n_samples, after.excitation_hz) == (1, 500, 60e3)
    assert after.boot_id != boot_id and after.measurement_id == 1


def test_a_resent_acquire_is_replayed_from_the_cache_and_error_replies_are_not_cached():
    node = make_node()
    current = answer(ask(node, AcquireRequest(0)))
    first = ask(node, ComputeDiRequest(current.measurement_id), request_id=555)
    assert answer(first).code == ErrorCode.NO_BASELINE
    ask(node, AcquireRequest(1))
    again = ask(node, ComputeDiRequest(current.measurement_id), request_id=555)
    assert again[0].msg_type == ComputeDiRequest.TYPE | 0x80 and not again[0].flags & FLAG_CACHED
    replay = ask(node, ComputeDiRequest(current.measurement_id), request_id=555)
    assert replay[0].flags == FLAG_REPLY | FLAG_LAST | FLAG_CACHED and replay[0].payload == again[0].payload


def test_a_node_without_on_board_di_answers_its_commands_unknown():
    node = make_node(firmware={"capabilities": ["baseline_slot", "chunk_retransmit"]})
    assert answer(ask(node, InfoRequest(1, 2), version=1)).capabilities == 0b110
    for request in (ComputeDiRequest(1), ReadDiRequest(1)):
        assert answer(ask(node, request)).code == ErrorCode.UNKNOWN_COMMAND


def test_a_node_without_a_baseline_slot_refuses_a_baseline_acquisition():
    node = make_node(firmware={"capabilities": ["on_board_di", "chunk_retransmit"]})
    assert answer(ask(node, AcquireRequest(1))).code == ErrorCode.BAD_ARGUMENT
    assert answer(ask(node, StatusRequest())).n_measurements == 0


def test_a_node_without_chunk_retransmission_refuses_a_chunk_list_and_serves_whole_transfers():
    node = make_node(firmware={"capabilities": ["on_board_di", "baseline_slot"]})
    acquired = answer(ask(node, AcquireRequest(0)))
    assert answer(ask(node, ReadTracesRequest(acquired.measurement_id, 1, 0, 0, (0,)))).code == ErrorCode.BAD_ARGUMENT
    assert len(ask(node, ReadTracesRequest(acquired.measurement_id, 1, 0, 0))) == 2  # meta + one chunk


def test_chunk_lists_are_answered_once_each_in_ascending_order():
    node = make_node(n_samples=6000)
    acquired = answer(ask(node, AcquireRequest(0)))
    frames = ask(node, ReadTracesRequest(acquired.measurement_id, 0xFFFF, 0, 0, (7, 3, 7, 0)))
    chunks = [decode_message(f.msg_type, f.payload) for f in frames[1:]]
    assert [c.index for c in chunks] == [0, 3, 7] and frames[-1].flags & FLAG_LAST


def test_while_acquiring_a_busy_node_answers_busy_but_info_and_status_at_once():
    clock = FakeClock()
    node = make_node(clock, firmware={"busy_while_acquiring": True})
    ask(node, ConfigureRequest(85e3, 5, 100, 0xFFFF, 600))
    ask(node, AcquireRequest(0), request_id=9)
    assert node.last_service_s == pytest.approx(0.5)
    busy = answer(ask(node, ReadTracesRequest(1, 1, 0, 10)))
    assert isinstance(busy, ErrorReply) and busy.code == ErrorCode.BUSY
    assert ask(node, AcquireRequest(0), request_id=9) == []  # its reply is on the way
    status = answer(ask(node, StatusRequest()))
    assert isinstance(status, StatusReply) and status.busy == 1
    clock.now_s += 0.5
    assert answer(ask(node, StatusRequest())).busy == 0
    assert isinstance(answer(ask(node, AcquireRequest(0))), AcquireReply)

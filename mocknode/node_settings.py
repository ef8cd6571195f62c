"""The mock node's acquisition settings (pure): those in force after a boot, the checks CONFIGURE
makes before it applies new ones, and the scenario an acquisition runs with them."""
from __future__ import annotations

import math

import numpy as np

from mocknode.recorded import RecordedPipe
from mocknode.refusal import Refused
from mocknode.scenario import NodeScenario
from protocol.messages import ConfigureReply, ConfigureRequest, ErrorCode


def power_up_settings(scenario: NodeScenario) -> ConfigureReply:
    """The settings in force after a boot: the scenario's ``power_up`` keys, else its own."""
    scn, up = scenario, scenario.power_up
    return ConfigureReply(
        float(np.float32(up.excitation_hz or scn.excitation.frequency_hz)), up.cycles or scn.excitation.cycles,
        up.averaging or scn.acquisition.averaging, (1 << len(scn.rings.rx_angles)) - 1,
        up.n_samples or scn.acquisition.n_samples,
    )


def max_samples(scenario: NodeScenario, recorded: RecordedPipe | None) -> int:
    """The longest record CONFIGURE accepts: the firmware's limit; a replayed record, no longer than
    it was simulated."""
    if recorded is not None:
        return min(scenario.max_samples, recorded.n_samples)
    return scenario.max_samples


def configured(message: ConfigureRequest, scenario: NodeScenario, recorded: RecordedPipe | None,
               clamps: bool) -> ConfigureReply:
    """The settings CONFIGURE applies, or :class:`Refused` (BAD_ARGUMENT) naming the first one out of
    range; ``clamps`` (a violation) clamps averaging and n_samples instead of refusing them."""
    n_rx = len(scenario.rings.rx_angles)
    if not (1e3 <= message.excitation_hz <= 1e6 and math.isfinite(message.excitation_hz)):
        raise Refused(ErrorCode.BAD_ARGUMENT, "excitation_hz outside 1 kHz..1 MHz")
    if not 1 <= message.cycles <= 50:
        raise Refused(ErrorCode.BAD_ARGUMENT, "cycles outside 1..50")
    averaging, n_samples, longest = message.averaging, message.n_samples, max_samples(scenario, recorded)
    if clamps:
        averaging, n_samples = min(averaging, 10000), min(n_samples, longest)
    if not 1 <= averaging <= 10000:
        raise Refused(ErrorCode.BAD_ARGUMENT, "averaging outside 1..10000")
    if message.channel_mask == 0 or message.channel_mask >> n_rx:
        raise Refused(ErrorCode.BAD_ARGUMENT, f"channel_mask must select channels of 0..{n_rx - 1}")
    if not 2 <= n_samples <= longest:
        raise Refused(ErrorCode.BAD_ARGUMENT, f"n_samples outside 2..{longest}")
    record = recorded.baseline if recorded is not None else None
    if record is not None and not (math.isclose(message.excitation_hz, record.excitation_hz, rel_tol=1e-6)
                                   and message.cycles == record.cycles):
        raise Refused(ErrorCode.BAD_ARGUMENT, f"this node replays full-wave records of {record.excitation_hz:g} Hz, "
                                              f"{record.cycles} cycles only")
    return ConfigureReply(float(np.float32(message.excitation_hz)), message.cycles, averaging,
                          message.channel_mask, n_samples)


def configured_scenario(scenario: NodeScenario, config: ConfigureReply) -> NodeScenario:
    """``scenario`` with the excitation and acquisition settings of ``config``."""
    scn, cfg = scenario, config
    return scn.model_copy(update={
        "excitation": scn.excitation.model_copy(update={"frequency_hz": cfg.excitation_hz, "cycles": cfg.cycles}),
        "acquisition": scn.acquisition.model_copy(update={"averaging": cfg.averaging, "n_samples": cfg.n_samples}),
    })

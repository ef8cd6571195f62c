"""PipeSentry's own full-wave cases: baseline/current pairs with their truth, unlike the dev set's.

Every case is a pair of simulations (the baseline: the pipe without the defects, at the baseline
temperature) and what the node's receiver chain does to them (fullwave/acquisition.py). The
list deliberately differs from /work/shared/fullwave-dev: other positions and angles, other
notch sizes, 8-transducer rings with notches and 16-transducer rings with masses, two defects
of different strengths, rings placed off the pipe's middle (so the two end echoes do not
coincide), the mid-wall circumference as the wave's path (the record reports pi x OD), and
cases of the in-plane model (mode conversion, tilted transducers). Names start with ``fw_``.

Truth follows the dev set's manifest: defects with ``axial_mm`` from the Tx ring, ``angle_deg``,
``kind`` and ``size``; ``ends``, ``transducers``, ``excitation_hz``, ``fs_hz``,
``temperature_change_c``, ``noisy``; plus this engine's own keys (``model``, ``decimation``,
``tx_axial_mm``, ``pipe_length_mm``, ``tilt_deg``, ``wave_circumference_mm``).
"""
from __future__ import annotations

import dataclasses
import hashlib
from dataclasses import dataclass

from fullwave.defects import Defect, Mass, Notch, describe
from fullwave.record import PipeModel, SimulationSpec
from fullwave.transducers import RingLayout

HEAVY = {"diameter_mm": 6.0, "mass_kg": 10.0}  # near-rigid point (the paper's clamp)
LIGHT = {"diameter_mm": 20.0, "mass_kg": 1.0}
PAPER_NOTCH = {"circumferential_mm": 20.0, "axial_length_mm": 10.0, "depth_mm": 2.0}
DEEP_NOTCH = {"circumferential_mm": 20.0, "axial_length_mm": 10.0, "depth_mm": 3.0}
WIDE_NOTCH = {"circumferential_mm": 35.0, "axial_length_mm": 8.0, "depth_mm": 1.5}
SMALL_NOTCH = {"circumferential_mm": 15.0, "axial_length_mm": 5.0, "depth_mm": 1.0}
DECIMATED_FACTOR = 10  # 10 MHz -> 1 MHz, as the node's FPGA map uses
CASE_CELL_MM = 0.5  # grid converged to a few % on the change a defect makes (docs/fullwave.md)


@dataclass(frozen=True)
class Case:
    """One baseline/current pair and what the receiver chain adds."""

    name: str
    baseline: SimulationSpec
    current: SimulationSpec
    noisy: bool = False
    decimation: int = 1

    @property
    def defects(self) -> tuple[Defect, ...]:
        return self.current.defects

    @property
    def seed(self) -> int:
        """Noise seed, fixed by the name (so a case's records are reproducible)."""
        return int.from_bytes(hashlib.sha256(self.name.encode()).digest()[:8], "little")

    def manifest_entry(self) -> dict:
        spec = self.current
        return {
            "case": self.name,
            "baseline": f"{self.name}_baseline.npz",
            "current": f"{self.name}_current.npz",
            "defects": [describe(d) for d in self.defects],
            "ends": spec.pipe.ends,
            "transducers": spec.rings.n_transducers,
            "excitation_hz": spec.excitation_hz,
            "fs_hz": spec.fs_hz / self.decimation,
            "temperature_change_c": round(spec.temperature_c - self.baseline.temperature_c, 6),
            "noisy": self.noisy,
            "model": spec.model,
            "decimation": self.decimation,
            "tx_axial_mm": spec.rings.tx_axial_mm,
            "pipe_length_mm": spec.pipe.length_mm,
            "tilt_deg": spec.rings.tilt_deg,
            "wave_circumference_mm": round(spec.pipe.wave_circumference_mm, 3),
            "cell_mm": spec.cell_mm,
        }

    def with_cell(self, cell_mm: float) -> Case:
        """The same case on another grid (a coarse one for a quick look)."""
        return dataclasses.replace(self, baseline=self.baseline.with_changes(cell_mm=cell_mm),
                                   current=self.current.with_changes(cell_mm=cell_mm))


def _spec(ends: str, n: int, frequency_hz: float, *, model: str = "sh", tx_axial_mm: float = 300.0,
          length_mm: float = 1000.0, tilt_deg: float = 0.0) -> SimulationSpec:
    return SimulationSpec(
        pipe=PipeModel(ends=ends, length_mm=length_mm),  # type: ignore[arg-type]
        rings=RingLayout(tx_axial_mm=tx_axial_mm, n_transducers=n, tilt_deg=tilt_deg),
        excitation_hz=frequency_hz,
        model=model,  # type: ignore[arg-type]
        cell_mm=CASE_CELL_MM,
    )


def _case(name: str, base: SimulationSpec, defects: tuple[Defect, ...], *, dt_c: float = 0.0,
          noisy: bool = False, decimation: int = 1) -> Case:
    current = dataclasses.replace(base, defects=defects, temperature_c=base.temperature_c + dt_c)
    return Case(name, base, current, noisy, decimation)


def _with_variants(case: Case, *, noisy: bool = True, decimated: bool = False) -> list[Case]:
    """The clean case, its noisy twin, and (``decimated``) a noisy one at 1 MHz."""
    out = [case]
    if noisy:
        out.append(dataclasses.replace(case, name=f"{case.name}_noisy", noisy=True))
    if decimated:
        out.append(dataclasses.replace(case, name=f"{case.name}_decim", noisy=True, decimation=DECIMATED_FACTOR))
    return out


def _notch(axial: float, angle: float, size: dict = PAPER_NOTCH) -> Notch:
    return Notch(axial_mm=axial, angle_deg=angle, **size)


def _mass(axial: float, angle: float, size: dict = HEAVY) -> Mass:
    return Mass(axial_mm=axial, angle_deg=angle, **size)


def _sh_cases() -> list[Case]:
    n16r, n16a = _spec("reflecting", 16, 85e3), _spec("absorbing", 16, 85e3)
    m8r, m8a = _spec("reflecting", 8, 75e3), _spec("absorbing", 8, 75e3)
    m8r85, m8a85 = _spec("reflecting", 8, 85e3), _spec("absorbing", 8, 85e3)
    n16r75, n16a75 = _spec("reflecting", 16, 75e3), _spec("absorbing", 16, 75e3)
    asym = _spec("reflecting", 16, 85e3, tx_axial_mm=200.0)
    asym_a = _spec("absorbing", 16, 85e3, tx_axial_mm=200.0)
    asym_m8 = _spec("reflecting", 8, 75e3, tx_axial_mm=250.0, length_mm=1200.0)
    cases: list[Case] = []
    add = cases.extend
    # notches, 16 transducers at 85 kHz, both ends
    add(_with_variants(_case("fw_n16_reflecting_notch_80_100", n16r, (_notch(80, 100),))))
    add(_with_variants(_case("fw_n16_reflecting_notch_200_250", n16r, (_notch(200, 250),)), decimated=True))
    add(_with_variants(_case("fw_n16_reflecting_notch_320_10", n16r, (_notch(320, 10),))))
    add(_with_variants(_case("fw_n16_reflecting_notch_30_45", n16r, (_notch(30, 45),)), noisy=False))
    add(_with_variants(_case("fw_n16_reflecting_notch_375_225", n16r, (_notch(375, 225),)), noisy=False))
    add(_with_variants(_case("fw_n16_reflecting_deep_270_160", n16r, (_notch(270, 160, DEEP_NOTCH),))))
    add(_with_variants(_case("fw_n16_reflecting_wide_130_300", n16r, (_notch(130, 300, WIDE_NOTCH),))))
    add(_with_variants(_case("fw_n16_reflecting_small_240_75", n16r, (_notch(240, 75, SMALL_NOTCH),))))
    add(_with_variants(_case("fw_n16_absorbing_notch_80_100", n16a, (_notch(80, 100),))))
    add(_with_variants(_case("fw_n16_absorbing_notch_200_250", n16a, (_notch(200, 250),)), decimated=True))
    add(_with_variants(_case("fw_n16_absorbing_notch_320_10", n16a, (_notch(320, 10),))))
    add(_with_variants(_case("fw_n16_absorbing_small_240_75", n16a, (_notch(240, 75, SMALL_NOTCH),))))
    # notches seen by 8-transducer rings at 85 kHz (the ring-order helical mode propagates)
    add(_with_variants(_case("fw_m8_reflecting_notch_180_70", m8r85, (_notch(180, 70),))))
    add(_with_variants(_case("fw_m8_absorbing_notch_240_290", m8a85, (_notch(240, 290),))))
    # masses: 8 transducers at 75 kHz, heavy and light, both ends
    add(_with_variants(_case("fw_m8_reflecting_mass_120_200", m8r, (_mass(120, 200),)), decimated=True))
    add(_with_variants(_case("fw_m8_absorbing_mass_280_330", m8a, (_mass(280, 330),))))
    add(_with_variants(_case("fw_m8_reflecting_light_200_100", m8r, (_mass(200, 100, LIGHT),))))
    add(_with_variants(_case("fw_m8_absorbing_light_330_250", m8a, (_mass(330, 250, LIGHT),))))
    # masses seen by 16-transducer rings at 75 kHz
    add(_with_variants(_case("fw_n16_reflecting_mass_220_60", n16r75, (_mass(220, 60),))))
    add(_with_variants(_case("fw_n16_absorbing_light_90_180", n16a75, (_mass(90, 180, LIGHT),))))
    # two defects of different strengths
    add(_with_variants(_case("fw_n16_reflecting_two_deep_110_40_small_290_210", n16r,
                             (_notch(110, 40, DEEP_NOTCH), _notch(290, 210, SMALL_NOTCH)))))
    add(_with_variants(_case("fw_n16_absorbing_notch_150_300_light_330_120", n16a,
                             (_notch(150, 300), _mass(330, 120, LIGHT)))))
    add(_with_variants(_case("fw_m8_reflecting_mass_90_0_light_310_180", m8r,
                             (_mass(90, 0), _mass(310, 180, LIGHT)))))
    # temperature between baseline and current
    add(_with_variants(_case("fw_n16_reflecting_notch_200_250_dTp4", n16r, (_notch(200, 250),), dt_c=4.0)))
    add(_with_variants(_case("fw_n16_absorbing_notch_80_100_dTm5", n16a, (_notch(80, 100),), dt_c=-5.0)))
    add(_with_variants(_case("fw_m8_reflecting_mass_120_200_dTp3", m8r, (_mass(120, 200),), dt_c=3.0)))
    # ... beside a strong scatterer, whose change can buy a stretch of its own (docs/imaging.md)
    add(_with_variants(_case("fw_m8_absorbing_light_330_250_dTp12", m8a, (_mass(330, 250, LIGHT),), dt_c=12.0)))
    add(_with_variants(_case("fw_m8_reflecting_light_200_100_dTm10", m8r, (_mass(200, 100, LIGHT),), dt_c=-10.0)))
    add(_with_variants(_case("fw_m8_absorbing_mass_280_330_dTp8", m8a, (_mass(280, 330),), dt_c=8.0)))
    # rings off the pipe's middle: the two end echoes no longer coincide
    add(_with_variants(_case("fw_n16_reflecting_asym_notch_160_210", asym, (_notch(160, 210),))))
    add(_with_variants(_case("fw_n16_absorbing_asym_notch_340_130", asym_a, (_notch(340, 130),))))
    add(_with_variants(_case("fw_m8_reflecting_asym_mass_260_40", asym_m8, (_mass(260, 40),))))
    # defect-free pairs: a small temperature change (and noise) only; no detection is right
    for name, base, dt_c in (("fw_n16_reflecting_fa_p04", n16r, 0.4), ("fw_n16_reflecting_fa_m07", n16r, -0.7),
                             ("fw_n16_absorbing_fa_p05", n16a, 0.5), ("fw_m8_reflecting_fa_m03", m8r, -0.3),
                             ("fw_m8_absorbing_fa_p06", m8a, 0.6), ("fw_n16_reflecting_asym_fa_p03", asym, 0.3)):
        add(_with_variants(_case(name, base, (), dt_c=dt_c)))
    return cases


TILT_DEG = 10.0  # a shear patch turned 10 deg towards the axis: L(0,2) at ~2 % of T(0,1) in the record


def _inplane_cases() -> list[Case]:
    """The in-plane model: mode conversion at the defects, and (tilted patches) L(0,2) from the rings.
    The first two repeat SH cases' defects, so the two models can be compared on the same pipe."""
    n16r, n16a = _spec("reflecting", 16, 85e3, model="inplane"), _spec("absorbing", 16, 85e3, model="inplane")
    n16r_t = _spec("reflecting", 16, 85e3, model="inplane", tilt_deg=TILT_DEG)
    m8r_t = _spec("reflecting", 8, 75e3, model="inplane", tilt_deg=TILT_DEG)
    cases: list[Case] = []
    add = cases.extend
    add(_with_variants(_case("fw_ip_n16_reflecting_notch_200_250", n16r, (_notch(200, 250),))))
    add(_with_variants(_case("fw_ip_n16_absorbing_notch_80_100", n16a, (_notch(80, 100),))))
    add(_with_variants(_case("fw_ip_n16_reflecting_tilt10_notch_320_10", n16r_t, (_notch(320, 10),))))
    add(_with_variants(_case("fw_ip_m8_reflecting_tilt10_mass_120_200", m8r_t, (_mass(120, 200),))))
    add(_with_variants(_case("fw_ip_n16_reflecting_tilt10_fa_p04", n16r_t, (), dt_c=0.4)))
    add(_with_variants(_case("fw_ip_m8_reflecting_tilt10_fa_m03", m8r_t, (), dt_c=-0.3)))
    return cases


def own_cases() -> list[Case]:
    """The project's own full-wave cases, in a stable order (names are unique)."""
    return _sh_cases() + _inplane_cases()


__all__ = ["CASE_CELL_MM", "DECIMATED_FACTOR", "TILT_DEG", "Case", "own_cases"]

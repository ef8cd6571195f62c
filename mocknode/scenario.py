"""What a simulated node is: its pipe, rings, excitation, acquisition chain, defects and weather.

Pydantic models loaded from TOML (or YAML when pyyaml is installed). Every model forbids
unknown keys, so a typo in a scenario file fails loudly with the offending key named.
Lengths are millimetres, times seconds, frequencies hertz, voltages volts.
"""
from __future__ import annotations

import copy
import math
import tomllib
from pathlib import Path
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, ValidationInfo, field_validator, model_validator

from mocknode.faults import FaultSpec


class ScenarioError(ValueError):
    """A scenario file or dict is unreadable or invalid; ``key`` names the offending entry."""

    def __init__(self, message: str, key: str | None = None) -> None:
        self.key = key
        super().__init__(f"{key}: {message}" if key else message)


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class PipeSpec(_Strict):
    """Straight steel pipe carrying a non-dispersive T(0,1) wave (paper, Table 1)."""

    outer_diameter_mm: float = Field(114.6, gt=0)
    wall_mm: float = Field(4.0, gt=0)
    length_mm: float = Field(1000.0, gt=0)
    velocity_m_s: float = Field(3130.0, gt=0, description="T(0,1) group velocity at TemperatureSpec.reference_c")
    velocity_temp_coeff_per_c: float = Field(
        1e-4, ge=0, lt=0.01, description="fractional velocity drop per degC: c(T) = c0 (1 - k (T - Tref))"
    )
    ends: Literal["reflecting", "absorbing"] = "reflecting"
    end_reflection: float | None = Field(
        None, ge=0.0, le=1.0, description="override the ends' T(0,1) reflection coefficient (free end 1.0, absorbing 0.01)"
    )

    @model_validator(mode="after")
    def _wall_fits(self) -> PipeSpec:
        if self.wall_mm * 2 >= self.outer_diameter_mm:
            raise ValueError("wall_mm must be less than half of outer_diameter_mm")
        return self

    @property
    def reflection_coefficient(self) -> float:
        """T(0,1) displacement reflection coefficient of each pipe end."""
        if self.end_reflection is not None:
            return self.end_reflection
        return 1.0 if self.ends == "reflecting" else ABSORBING_END_REFLECTION

    @property
    def outer_circumference_mm(self) -> float:
        return math.pi * self.outer_diameter_mm

    @property
    def propagation_circumference_mm(self) -> float:
        """Mid-wall circumference: the wrap length a scattered wave travels round the pipe."""
        return math.pi * (self.outer_diameter_mm - self.wall_mm)


ABSORBING_END_REFLECTION = 0.01  # COMSOL "low-reflecting" boundaries leave ~1 % (assumed)


def _equal_angles(n: int) -> list[float]:
    return [360.0 * i / n for i in range(n)]


class RingSpec(_Strict):
    """Tx ring and Rx ring geometry: positions, transducer count and width."""

    tx_axial_mm: float = Field(300.0, ge=0, description="Tx ring position from the pipe end behind it")
    tx_rx_distance_mm: float = Field(400.0, gt=0)
    n_transducers: int = Field(
        16, ge=1, le=64, description="per ring; the paper uses 16 (FE) or 8 (experiment); a served node carries <= 32"
    )
    transducer_width_mm: float = Field(15.0, gt=0, description="circumferential width of each PZT")
    transducer_length_mm: float = Field(15.0, ge=0, description="axial length of each PZT")
    tx_angles_deg: list[float] | None = None
    rx_angles_deg: list[float] | None = None

    @field_validator("tx_angles_deg", "rx_angles_deg")
    @classmethod
    def _angles_in_range(cls, value: list[float] | None) -> list[float] | None:
        if value is not None and not all(math.isfinite(a) and 0.0 <= a < 360.0 for a in value):
            raise ValueError("angles must be finite and in [0, 360) degrees")
        return value

    @model_validator(mode="after")
    def _angle_counts(self) -> RingSpec:
        for name in ("tx_angles_deg", "rx_angles_deg"):
            value = getattr(self, name)
            if value is not None and len(value) != self.n_transducers:
                raise ValueError(f"{name} lists {len(value)} angles but n_transducers is {self.n_transducers}")
        return self

    @property
    def tx_angles(self) -> list[float]:
        return list(self.tx_angles_deg) if self.tx_angles_deg is not None else _equal_angles(self.n_transducers)

    @property
    def rx_angles(self) -> list[float]:
        return list(self.rx_angles_deg) if self.rx_angles_deg is not None else _equal_angles(self.n_transducers)


class ExcitationSpec(_Strict):
    """n-cycle Hann-windowed sine H(t) = 0.5 (1 - cos(2 pi f t / n)) sin(2 pi f t), 0 <= t <= n/f."""

    frequency_hz: float = Field(85e3, gt=0, description="85 kHz for the notch cases, 75 kHz for mass loading")
    cycles: int = Field(5, ge=1, le=50)


class AcquisitionSpec(_Strict):
    """Receiver chain of the FPGA node: sampling, averaging, noise, ADC and decimation."""

    fs_hz: float = Field(10e6, gt=0)
    n_samples: int = Field(6000, ge=2, le=1_000_000)
    t0_s: float = Field(0.0, description="time of sample 0 after the excitation starts")
    averaging: int = Field(10, ge=1, le=100_000, description="shots averaged per measurement")
    adc_bits: int = Field(10, ge=2, le=16)
    adc_full_scale_v: float = Field(0.25, gt=0, description="peak input voltage of the ADC (codes clip beyond it)")
    noise_v_rms: float = Field(2e-3, ge=0, description="white receiver noise per single shot, volts RMS")
    direct_amplitude_v: float = Field(
        0.0825, gt=0, description="peak of the direct T(0,1) arrival at a receiver (paper, Table 3: 82.5 mV)"
    )
    decimation: int = Field(10, ge=1, le=1000, description="on-board decimation factor for the FPGA's DI map")

    @field_validator("t0_s")
    @classmethod
    def _finite(cls, value: float) -> float:
        if not math.isfinite(value):
            raise ValueError("must be finite")
        return value


class NotchSize(_Strict):
    """Part-depth notch: paper's FE notch is 20 mm round, 10 mm long, 2 mm deep."""

    circumferential_mm: float = Field(20.0, gt=0)
    axial_mm_len: float = Field(10.0, gt=0)
    depth_mm: float = Field(2.0, gt=0)


class MassSize(_Strict):
    """Added mass (C-clamp) on a small contact patch: paper uses 10 kg on a 6 mm circle."""

    diameter_mm: float = Field(6.0, gt=0)
    mass_kg: float = Field(10.0, gt=0)


class GrowthSpec(_Strict):
    """Strength ramps linearly from ``start_strength`` to the final strength over ``grow_duration_s``."""

    start_strength: float = Field(0.0, ge=0)
    final_strength: float | None = Field(None, ge=0, description="None: the defect's own strength")
    grow_duration_s: float = Field(gt=0)


class DefectSpec(_Strict):
    """One scatterer: where it is (axial from the Tx ring, angle), what it is, and when it appears."""

    kind: Literal["notch", "mass"]
    axial_mm: float = Field(description="axial position measured from the Tx ring (Rx ring at tx_rx_distance_mm)")
    angle_deg: float = Field(ge=0.0, lt=360.0)
    size: NotchSize | MassSize
    strength: float | None = Field(
        None, ge=0, le=5.0, description="scattered amplitude / incident amplitude at one wavelength; None: from size"
    )
    appears_at_s: float = Field(0.0, ge=0, description="elapsed scenario time at which the defect appears")
    growth: GrowthSpec | None = None

    @model_validator(mode="before")
    @classmethod
    def _default_size_for_kind(cls, data: Any) -> Any:
        # An omitted or empty size means "the paper's size" for that kind; a non-empty table is
        # validated by the NotchSize | MassSize union (their keys are disjoint).
        if isinstance(data, dict) and not data.get("size"):
            kind = data.get("kind")
            size_model = {"notch": NotchSize, "mass": MassSize}.get(kind) if isinstance(kind, str) else None
            if size_model is not None:
                data = {**data, "size": size_model()}
        return data

    @model_validator(mode="after")
    def _size_matches_kind(self) -> DefectSpec:
        expected = NotchSize if self.kind == "notch" else MassSize
        if not isinstance(self.size, expected):
            keys = "/".join(expected.model_fields)
            raise ValueError(f"size: a {self.kind} takes {keys}")  # noqa: TRY004 (pydantic reports ValueError)
        return self


class TemperatureSpec(_Strict):
    """Pipe temperature: mean + daily sine + per-measurement jitter, degC."""

    reference_c: float = Field(20.0, description="temperature at which velocity_m_s holds")
    mean_c: float = 20.0
    daily_amplitude_c: float = Field(0.0, ge=0)
    period_s: float = Field(86400.0, gt=0)
    jitter_c: float = Field(0.0, ge=0, description="Gaussian standard deviation per measurement")


def _valid_mode(name: str) -> str:
    from mocknode.dispersion import DispersionError, parse_mode

    try:
        order_family = parse_mode(name)
    except DispersionError as exc:
        raise ValueError(str(exc)) from None
    if order_family == (0, 2):
        raise ValueError("T(0,1) is the main wave (direct arrival and defect scattering), not another mode")
    return name.strip()


class ModeLeak(_Strict):
    """A guided mode other than T(0,1) that the Tx ring also launches (both ways) and the Rx ring senses.

    ``amplitude`` is relative to T(0,1)'s, in the same wave units (before the transducers'
    aperture filters, which apply with the mode's own wavenumber); it lumps the Tx ring's
    excitation of the mode and the Rx transducers' sensitivity to it. The pattern round the
    Rx ring is cos(n (theta - angle_deg)); for a ring-order mode F(N, m) seen by N evenly spaced
    receivers that is the same at every receiver. Below its cut-off the mode is evanescent.
    """

    mode: str = Field(description="L(0,1), L(0,2) or F(n,m), m = 1 (A0-like), 2 (SH0-like), 3 (S0-like)")
    amplitude: float = Field(ge=0, le=2.0)
    phase_deg: float = 0.0
    angle_deg: float = Field(0.0, ge=0.0, lt=360.0, description="orientation of the cos(n theta) pattern")

    _mode_ok = field_validator("mode")(classmethod(lambda cls, v: _valid_mode(v)))


class ModeConversion(_Strict):
    """Every defect also scatters the incident T(0,1) into ``mode``, radiated both ways along the pipe.

    Amplitude at the receivers (before apertures): ``ratio`` x the defect's ring-level T(0,1)
    reflection |R_T| = strength * lambda / C, x cos(n (theta - theta_defect)); the phase is the
    defect's back-scatter phase plus ``phase_deg``. ``ratio`` lumps the conversion and the
    torsional receivers' partial sensitivity to the converted mode.
    """

    mode: str
    ratio: float = Field(ge=0, le=5.0)
    phase_deg: float = 0.0

    _mode_ok = field_validator("mode")(classmethod(lambda cls, v: _valid_mode(v)))


class ModesSpec(_Strict):
    """Guided modes besides T(0,1): leaks from the rings and conversion at defects (default: none).

    Dispersion: plate modes of the wall wound helically round the pipe (mocknode/dispersion.py).
    """

    leaks: list[ModeLeak] = Field(default_factory=list, max_length=32)
    conversions: list[ModeConversion] = Field(default_factory=list, max_length=16)
    poisson_ratio: float = Field(0.3, gt=0.0, lt=0.5, description="with the T(0,1) velocity, fixes c_L (paper: 0.3)")

    @property
    def active(self) -> bool:
        return bool(self.leaks or self.conversions)


class ReceiverFaultSpec(_Strict):
    """A receiver transducer that fails for a while: debonded or cable cut (gain near 0), degraded
    coupling (gain < 1), or moved / a longer cable (delay). Its electronic noise stays."""

    rx_index: int = Field(ge=0, description="row of the traces (receiver k sits at rx_angles_deg[k])")
    gain: float = Field(0.0, ge=0.0, le=10.0, description="signal kept: 0 dead, 0.3 badly coupled, 1 healthy")
    delay_s: float = Field(0.0, ge=-1e-4, le=1e-4, description="extra arrival delay of this channel")
    from_s: float = Field(0.0, ge=0.0, description="elapsed scenario time at which the fault starts")
    until_s: float | None = Field(None, gt=0.0, description="when it ends (None: never)")

    def active_at(self, elapsed_s: float) -> bool:
        return self.from_s <= elapsed_s and (self.until_s is None or elapsed_s < self.until_s)


Capability = Literal["on_board_di", "baseline_slot", "chunk_retransmit"]
ALL_CAPABILITIES: tuple[Capability, ...] = ("on_board_di", "baseline_slot", "chunk_retransmit")


class FirmwareSpec(_Strict):
    """What the node's firmware implements (INFO ``capabilities``, ``max_samples``) and how it
    behaves while it works; docs/protocol.md says what a node answers for what it lacks."""

    capabilities: list[Capability] = Field(
        default_factory=lambda: list(ALL_CAPABILITIES),
        description="INFO capability bits announced and honoured",
    )
    max_samples: int = Field(8000, ge=2, le=1_000_000, description="longest record CONFIGURE accepts (RAM)")
    busy_while_acquiring: bool = Field(
        False, description="an ACQUIRE takes averaging x shot period, during which commands other than INFO and "
        "STATUS are answered ERROR BUSY (else they wait behind it)"
    )


class PowerUpSpec(_Strict):
    """The settings in force after a (re)boot until the next CONFIGURE; unset keys take the
    scenario's ``excitation`` and ``acquisition`` values (what a gateway usually configures)."""

    excitation_hz: float | None = Field(None, ge=1e3, le=1e6)
    cycles: int | None = Field(None, ge=1, le=50)
    averaging: int | None = Field(None, ge=1, le=10_000)
    n_samples: int | None = Field(None, ge=2, le=1_000_000)


class FullwaveRecordsSpec(_Strict):
    """Serve precomputed full-wave records (fullwave/, docs/fullwave.md) instead of the ray physics.

    Until ``defect_appears_at_s`` every acquisition replays the ``baseline`` record, from then on the
    ``current`` one; the node's own receiver chain (receiver faults, noise, ADC) is applied on top, a
    fresh draw each time. The records fix the excitation, the rings and the temperature (each
    record's own); the pipe's ``defects``, ``temperature`` and ``modes`` are not simulated. A relative
    path is relative to the scenario file's folder.
    """

    baseline: Path
    current: Path
    defect_appears_at_s: float = Field(0.0, ge=0.0, description="scenario time at which the current record starts")

    @field_validator("baseline", "current")
    @classmethod
    def _relative_to_the_scenario(cls, value: Path, info: ValidationInfo) -> Path:
        base = (info.context or {}).get("base_dir")
        return value if value.is_absolute() or base is None else Path(base) / value


class NodeScenario(_Strict):
    """Everything needed to simulate one node's acquisitions over elapsed time."""

    node_id: str = Field(min_length=1, max_length=32, description="<= 32 bytes: the INFO reply's node-id field")
    seed: int = 0
    pipe: PipeSpec = PipeSpec()
    rings: RingSpec = RingSpec()
    excitation: ExcitationSpec = ExcitationSpec()
    acquisition: AcquisitionSpec = AcquisitionSpec()
    defects: list[DefectSpec] = Field(default_factory=list, max_length=32)
    temperature: TemperatureSpec = TemperatureSpec()
    faults: FaultSpec = FaultSpec()
    modes: ModesSpec = ModesSpec()
    receiver_faults: list[ReceiverFaultSpec] = Field(default_factory=list, max_length=64)
    firmware: FirmwareSpec = FirmwareSpec()
    power_up: PowerUpSpec = PowerUpSpec()

    @property
    def max_samples(self) -> int:
        """The longest record the node accepts: the firmware's limit, never below its own defaults."""
        return max(self.firmware.max_samples, self.acquisition.n_samples, self.power_up.n_samples or 0)
    fullwave: FullwaveRecordsSpec | None = None

    @model_validator(mode="after")
    def _geometry_fits(self) -> NodeScenario:
        rings, pipe = self.rings, self.pipe
        if rings.tx_axial_mm + rings.tx_rx_distance_mm > pipe.length_mm:
            raise ValueError(
                f"the Rx ring at {rings.tx_axial_mm + rings.tx_rx_distance_mm} mm from the end lies beyond "
                f"the {pipe.length_mm} mm pipe"
            )
        if rings.n_transducers * rings.transducer_width_mm > pipe.outer_circumference_mm:
            raise ValueError("the transducers of a ring do not fit round the pipe (n_transducers * width)")
        near_end, far_end = -rings.tx_axial_mm, pipe.length_mm - rings.tx_axial_mm
        for i, defect in enumerate(self.defects):
            if not near_end <= defect.axial_mm <= far_end:
                raise ValueError(
                    f"defects[{i}].axial_mm={defect.axial_mm} lies outside the pipe ({near_end}..{far_end} mm)"
                )
        for i, fault in enumerate(self.receiver_faults):
            if fault.rx_index >= rings.n_transducers:
                raise ValueError(
                    f"receiver_faults[{i}].rx_index={fault.rx_index}: the ring has {rings.n_transducers} receivers"
                )
            if fault.until_s is not None and fault.until_s <= fault.from_s:
                raise ValueError(f"receiver_faults[{i}]: until_s must be after from_s")
        return self


def _deep_merge(base: dict, override: dict) -> dict:
    """``override`` wins; nested tables merge key by key (lists are replaced, not merged)."""
    merged = copy.deepcopy(base)
    for key, value in override.items():
        if isinstance(value, dict) and isinstance(merged.get(key), dict):
            merged[key] = _deep_merge(merged[key], value)
        else:
            merged[key] = copy.deepcopy(value)
    return merged


class Scenario(_Strict):
    """A fleet of simulated nodes; ``defaults`` is merged under every node's own settings."""

    defaults: dict[str, Any] = Field(default_factory=dict)
    nodes: list[NodeScenario] = Field(min_length=1, max_length=256)

    @model_validator(mode="before")
    @classmethod
    def _apply_defaults(cls, data: Any) -> Any:
        if not isinstance(data, dict):
            return data
        defaults = data.get("defaults") or {}
        nodes = data.get("nodes")
        if not isinstance(defaults, dict) or not isinstance(nodes, list):
            return data
        if "node_id" in defaults:
            raise ValueError("defaults may not set node_id")
        data = dict(data)
        data["nodes"] = [_deep_merge(defaults, n) if isinstance(n, dict) else n for n in nodes]
        return data

    @model_validator(mode="after")
    def _unique_ids(self) -> Scenario:
        ids = [n.node_id for n in self.nodes]
        dupes = sorted({i for i in ids if ids.count(i) > 1})
        if dupes:
            raise ValueError(f"duplicate node_id: {', '.join(dupes)}")
        return self

    def node(self, node_id: str) -> NodeScenario:
        for n in self.nodes:
            if n.node_id == node_id:
                return n
        raise ScenarioError("no such node", key=node_id)


def _error_key(exc: ValidationError) -> tuple[str | None, str]:
    first = exc.errors(include_url=False)[0]
    # Drop pydantic's union/validator tags ("function-after[...]", "NotchSize") from the path.
    parts = [str(p) for p in first["loc"] if not (isinstance(p, str) and ("[" in p or p[:1].isupper()))]
    return (".".join(parts) or None), first["msg"]


def scenario_from_dict(data: dict, base_dir: Path | None = None) -> Scenario:
    """Validate a parsed scenario document; raises ScenarioError naming the first bad key.
    Relative file paths in it (full-wave records) are taken from ``base_dir``."""
    try:
        return Scenario.model_validate(data, context={"base_dir": base_dir})
    except ValidationError as exc:
        key, msg = _error_key(exc)
        raise ScenarioError(msg, key=key) from exc


def load_scenario(path: str | Path) -> Scenario:
    """Read a .toml (or .yaml/.yml, if pyyaml is installed) scenario file."""
    path = Path(path)
    try:
        text = path.read_bytes()
    except OSError as exc:
        raise ScenarioError(f"cannot read scenario file: {exc.strerror}", key=str(path)) from exc
    suffix = path.suffix.lower()
    if suffix in (".yaml", ".yml"):
        try:
            import yaml  # optional dependency
        except ImportError as exc:
            raise ScenarioError("YAML scenarios need pyyaml; use TOML instead", key=str(path)) from exc
        try:
            data = yaml.safe_load(text)
        except yaml.YAMLError as exc:
            raise ScenarioError(f"invalid YAML: {exc}", key=str(path)) from exc
    else:
        try:
            data = tomllib.loads(text.decode("utf-8"))
        except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
            raise ScenarioError(f"invalid TOML: {exc}", key=str(path)) from exc
    if not isinstance(data, dict):
        raise ScenarioError("a scenario must be a table with a 'nodes' list", key=str(path))
    return scenario_from_dict(data, base_dir=path.parent)


DEMO_NOTCH_APPEARS_S = 120.0


def default_scenario(n_nodes: int) -> Scenario:
    """Demo fleet: all pipes start defect-free; node 1 grows the paper's notch (90 deg, 200 mm) after 2 min."""
    if not 1 <= n_nodes <= 256:
        raise ScenarioError(f"n_nodes must be 1..256, got {n_nodes}", key="n_nodes")
    weather = TemperatureSpec(mean_c=22.0, daily_amplitude_c=3.0, jitter_c=0.05)
    nodes = []
    for i in range(n_nodes):
        defects = []
        if i == 0:
            defects.append(
                DefectSpec(
                    kind="notch",
                    axial_mm=200.0,
                    angle_deg=90.0,
                    size=NotchSize(),
                    appears_at_s=DEMO_NOTCH_APPEARS_S,
                    growth=GrowthSpec(start_strength=0.05, grow_duration_s=600.0),
                )
            )
        nodes.append(NodeScenario(node_id=f"node-{i + 1:02d}", seed=1000 + i, defects=defects, temperature=weather))
    return Scenario(nodes=nodes)


__all__ = [
    "ABSORBING_END_REFLECTION",
    "AcquisitionSpec",
    "DefectSpec",
    "ExcitationSpec",
    "FirmwareSpec",
    "FullwaveRecordsSpec",
    "GrowthSpec",
    "MassSize",
    "ModeConversion",
    "ModeLeak",
    "ModesSpec",
    "NodeScenario",
    "NotchSize",
    "PipeSpec",
    "PowerUpSpec",
    "RingSpec",
    "Scenario",
    "ScenarioError",
    "TemperatureSpec",
    "default_scenario",
    "load_scenario",
    "scenario_from_dict",
]

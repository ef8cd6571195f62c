"""Temperature compensation: optimal baseline selection (OBS) and baseline signal stretch (BSS).

Warming slows the T(0,1) wave (about 1e-4 per degC in steel), so every arrival of the
current record comes a factor (1 + stretch) later than in a baseline taken colder, t counted
from the excitation start; the excitation burst itself is what it was, so the baseline is
stretched as the medium's response, not as a whole record (imaging/thermal.py). BSS finds that
factor by minimising the relative residual energy ||current - stretched||^2 / ||current||^2
over a bounded range (coarse grid, then a per-receiver refinement and their median); OBS does it for every
baseline of a library and keeps the best. When even the best leaves more than
``max_residual`` the library has no valid baseline and we abstain (``NoValidBaseline``)
rather than image against a wrong reference.
"""
from __future__ import annotations

import functools
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace

import numpy as np
from scipy import fft as sp_fft

from imaging.arrivals import hann_burst
from imaging.dimap import BaselineMismatch, check_compatible
from imaging.health import MAX_COMMON_GAIN_CHANGE, receiver_rows
from imaging.measurement import Measurement
from imaging.resample import Resampler
from imaging.thermal import ThermalStretch, recorded, slope_traces

DEFAULT_MAX_STRETCH = 0.005  # +-0.5 %: about +-50 degC of velocity change in steel
DEFAULT_MAX_RESIDUAL = 0.05  # relative residual energy above which no baseline is trusted
# Past this bound a record is not imaged but abstained on (assess()). Stretching the whole record
# had left a defect-free DI growing with |stretch| (FDTD 8-ring, free ends: 0.026 at +16 degC,
# threshold 0.02); with the medium's response stretched and the burst kept it stays at the noise
# floor to +-30 degC on both physics (bench/bench_thermal.py: <= 0.006). The bound now stands for
# what neither physics models: a temperature that is not uniform along the pipe, the transducers'
# and couplant's own temperature response, thermal expansion.
DEFAULT_MAX_COMPENSATED_STRETCH = 0.0015  # 0.15 %: about 15 degC in steel
STRETCH_PER_DEGC = 1.0e-4  # T(0,1) in steel: shear velocity -1e-4 per degC (the mock's model too)
# A strong scatterer's change can buy a stretch no temperature made (a near-rigid mass on a sparse
# ring: -1 to -2.5e-3 with no temperature change, project FDTD); the records' own temperatures
# then decide. The search and the thermometers disagree when they differ by more than this many
# degC plus this share of the thermometers' difference: more than a thermometer can plausibly be
# wrong by (a class-2 thermocouple's 2.5 degC, IEC 60584, and a few degC between where it sits and
# the wall between the rings, in a transient), the wall's velocity coefficient known to about a
# quarter. Measured (docs/accuracy.md): at 2.5 degC the override also fired on the full-wave sets'
# masses (spurious stretches of 3-6 degC) and made them worse; at 8 degC only on 10-25 degC ones.
THERMOMETER_TOLERANCE_C = 8.0
THERMOMETER_RELATIVE = 0.25
COARSE_STEPS = 21  # stretch grid of the first pass; a step of 0.05 % at +-0.5 %
SEARCH_DECIMATION = 16  # the search compares every 16th sample (7 per period at 85 kHz, 10 MHz: see below)
FINE_STEPS = 21  # second pass across the best coarse cell, per receiver
MIN_EXPLAINED = 0.06  # a stretch must remove >= 6 % of the unstretched residual energy to be used
MIN_GAIN_EXPLAINED = 0.5  # a common gain must remove >= half the in-band residual energy to be used
TIE_TOLERANCE = 0.05  # residuals within 5 % of the best count as a tie: take the smallest |stretch|
OBS_SHORTLIST = 3  # library entries (nearest by unstretched residual) that get the stretch search


class CompensationError(ValueError):
    """An empty library or bad search settings."""


@dataclass(frozen=True)
class BaselineMatch:
    """The baseline chosen for a current record: its library ``index``, the ``stretch`` applied, the
    remaining relative ``residual`` energy, the stretched ``baseline`` itself, and the ``gain`` common
    to the receivers it was scaled by (``with_common_gain``; 1.0: not scaled)."""

    index: int
    stretch: float
    residual: float
    baseline: Measurement
    gain: float = 1.0

    def as_dict(self) -> dict:
        return {"baseline_index": self.index, "stretch": self.stretch, "residual": self.residual, "gain": self.gain}


@dataclass(frozen=True)
class NoValidBaseline:
    """No baseline in the library matches the current record well enough: abstain, do not image."""

    best_index: int | None
    best_residual: float
    max_residual: float
    reason: str

    def as_dict(self) -> dict:
        return {
            "baseline_index": self.best_index,
            "residual": self.best_residual,
            "max_residual": self.max_residual,
            "reason": self.reason,
        }


def _sample_times_s(m: Measurement) -> np.ndarray:
    return m.t0_s + np.arange(m.n_samples) / m.fs_hz


def stretch_traces(m: Measurement, stretch: float) -> np.ndarray:
    """The traces as the pipe would give them with every wave (1 + stretch) slower: the medium's
    response stretched about the excitation start, the burst not (imaging/thermal.py)."""
    return ThermalStretch(m)(_sample_times_s(m), stretch)


def stretched(m: Measurement, stretch: float) -> Measurement:
    """A copy of ``m`` as if recorded with every arrival (1 + stretch) times later, the same burst."""
    if stretch == 0.0:
        return m
    return replace(m, traces=stretch_traces(m, stretch).astype(np.float32))


def _relative_residual(reference: np.ndarray, candidate: np.ndarray) -> float:
    energy = float(np.sum(reference * reference))
    diff = reference - candidate
    return float(np.sum(diff * diff)) / energy if energy > 0 else math.inf


def best_stretch(
    baseline: Measurement,
    current: Measurement,
    *,
    max_stretch: float = DEFAULT_MAX_STRETCH,
    rx_mask: np.ndarray | None = None,
) -> tuple[float, float]:
    """(stretch, relative residual) making the stretched baseline best match ``current``.

    Bounded to [-max_stretch, max_stretch]. A coarse grid of COARSE_STEPS finds the cell of
    the overall minimum; a fine grid of FINE_STEPS across that cell then gives each receiver's
    own best stretch (parabola through its three lowest points), and the stretch is their
    median. Both grids compare every SEARCH_DECIMATION-th sample. Temperature stretches every
    channel alike, whereas a defect's echo changes a few
    channels' residual (and, when it overlaps the direct arrival, looks like a small time
    shift on those channels only): the median keeps the echo out of the stretch.
    The stretch is used only if it removes at least MIN_EXPLAINED of the unstretched residual
    energy, else the stretch is 0. Measured: a synthetic scatterer alone (no temperature change)
    makes a spurious stretch that removes <= 5 %; on the mock node a +1..3 degC change removes
    7-49 % (least with absorbing ends, where noise dominates the record). A margin this thin
    is a known weakness: docs/accuracy.md. Receivers where ``rx_mask`` is False (faulty channels) are left out.
    """
    check_compatible(baseline, current)
    stretch, residual, _ = _stretch_search(baseline, current, max_stretch=max_stretch, rx_mask=rx_mask)
    return stretch, residual


def _stretch_search(baseline: Measurement, current: Measurement, *, max_stretch: float,
                    rx_mask: np.ndarray | None, gain: float = 1.0) -> tuple[float, float, np.ndarray]:
    """``best_stretch`` of a compatible pair, the baseline scaled by ``gain``, and the baseline's traces
    (so scaled) stretched by the answer (all receivers, float32).

    The baseline warmed by ``stretch`` is the medium's response stretched with the burst kept
    (imaging/thermal.py): to first order the record stretched plus stretch times the slope traces.
    Here the slope is taken of the *current* record, once per record, instead of each baseline's
    (equal to first order: the current is the warmed baseline; on the FDTD at -15..+30 degC it
    leaves 1.6e-6 to 7.3e-5 of the record against the exact model's 1.8e-6 to 6.2e-5). The search
    compares both records below 3 f0 (``_below_band``): interpolating the baseline at a fractional
    offset smooths its noise above the band, which lowers the cost of any stretch but 0 and had
    pulled the stretch of noisy dev-set records 0.15-0.25e-4 further from 0 than the clean ones'."""
    if not (0 <= max_stretch < 0.1):
        raise CompensationError(f"max_stretch must be in [0, 0.1), got {max_stretch}")
    rows = receiver_rows(current.n_rx, rx_mask)
    current_key = _traces_key(current)
    slope = _current_slope(current, current_key)
    times = _sample_times_s(current)
    target = current.traces[rows].astype(np.float64)
    if max_stretch > 0:
        sub = times[::SEARCH_DECIMATION]
        target_sub = _below_band(current, current_key)[rows, ::SEARCH_DECIMATION]
        slope_sub = slope[rows, ::SEARCH_DECIMATION]
        baseline_key = _traces_key(baseline)
        search = _below_band_spline(baseline, baseline_key, rows)

        def per_rx_cost(stretches: np.ndarray) -> np.ndarray:
            """Residual energy [n_stretches, n_rx] of each candidate, all evaluated at once; samples
            the stretched baseline does not cover count for nothing."""
            at = sub[None, :] / (1.0 + stretches[:, None])
            warmed = search(at).transpose(1, 0, 2)
            if gain != 1.0:
                warmed *= gain  # the spline is linear in the traces: the scaled baseline's
            diff = target_sub[None] - warmed - stretches[:, None, None] * slope_sub[None]
            diff *= recorded(at, baseline)[:, None, :]
            return np.sum(diff * diff, axis=2)

        coarse = np.linspace(-max_stretch, max_stretch, COARSE_STEPS)
        k = int(np.argmin(per_rx_cost(coarse).sum(axis=1)))
        step = coarse[1] - coarse[0]
        fine = np.linspace(coarse[k] - step, coarse[k] + step, FINE_STEPS)
        fine = fine[np.abs(fine) <= max_stretch + 1e-15]
        costs = per_rx_cost(fine)  # [n_fine, n_rx]
        best = float(np.clip(np.median([_parabola_min(fine, costs[:, m]) for m in range(costs.shape[1])]),
                             -max_stretch, max_stretch))
    else:
        best = 0.0
    plain = baseline.traces.astype(np.float64)
    as_recorded_traces = baseline.traces
    if gain != 1.0:
        as_recorded_traces = (plain * gain).astype(np.float32)  # what ``scaled`` gives
        plain = as_recorded_traces.astype(np.float64)
    plain_residual = _relative_residual(target, plain[rows])
    if best == 0.0:
        return 0.0, plain_residual, as_recorded_traces
    at = times / (1.0 + best)
    moved = _own_reference_where_unrecorded(Resampler(baseline)(at) * gain + best * slope, at, baseline, current)
    stretched_residual = _relative_residual(target, moved[rows])
    # Stretch only when it explains a good part of the difference: a defect's echo right after
    # the direct arrival also "prefers" a tiny delay, and stretching it away would bias the map.
    # Judged in the excitation's band: resampling at any fractional shift smooths the baseline's
    # noise above the band, which "explains" residual energy a stretch never did (white noise up
    # to Nyquist, no end echoes: a spurious 1e-4 accepted on most unchanged records).
    differences = np.empty((2,) + target.shape)
    np.subtract(target, plain[rows], out=differences[0])
    np.subtract(target, moved[rows], out=differences[1])
    plain_band, stretched_band = _in_band_energy(differences, current)
    if not stretched_band <= (1.0 - MIN_EXPLAINED) * plain_band:
        return 0.0, plain_residual, as_recorded_traces
    return best, stretched_residual, moved.astype(np.float32)


def _own_reference_where_unrecorded(warmed: np.ndarray, at_s: np.ndarray, baseline: Measurement,
                                    current: Measurement) -> np.ndarray:
    """``warmed`` (the baseline read at the times ``at_s``), with ``current``'s own samples wherever the
    baseline has none (a colder record's end holds what arrived after the baseline's): no change is
    claimed there. In place; returned."""
    uncovered = ~recorded(at_s, baseline)
    warmed[:, uncovered] = current.traces[:, uncovered]
    return warmed


def _traces_key(m: Measurement) -> tuple:
    """What a record's derived traces depend on: a digest of its traces and its acquisition setup."""
    return (*m.traces_digest(), m.fs_hz, m.t0_s, m.excitation_hz, m.cycles)


def _current_slope(m: Measurement, key: tuple) -> np.ndarray:
    """``slope_traces`` of the record (float64, read-only), derived once per record (``key``: ``_traces_key(m)``)."""
    def compute() -> np.ndarray:
        slope = slope_traces(m.traces, m)
        slope.setflags(write=False)
        return slope
    return m.derived("thermal_slope", key, compute)


def _band_limited(m: Measurement) -> np.ndarray:
    """The record's traces (float64) with what lies above the excitation's band removed: flat to 2 f0
    (where a 5-cycle burst's spectrum is below 1e-3 of its peak), a cosine taper to zero at 3 f0."""
    n = m.n_samples
    n_fft = sp_fft.next_fast_len(n, real=True)
    f = sp_fft.rfftfreq(n_fft, 1.0 / m.fs_hz) / m.excitation_hz
    response = np.where(f <= 2.0, 1.0, np.where(f >= 3.0, 0.0, 0.5 * (1.0 + np.cos(np.pi * (f - 2.0)))))
    return sp_fft.irfft(sp_fft.rfft(m.traces.astype(np.float64), n_fft, axis=-1) * response, n_fft, axis=-1)[:, :n]


def _below_band(m: Measurement, key: tuple) -> np.ndarray:
    """``_band_limited`` (read-only), derived once per record (the current, against each baseline
    searched; ``key``: ``_traces_key(m)``)."""
    def compute() -> np.ndarray:
        out = _band_limited(m)
        out.setflags(write=False)
        return out
    return m.derived("below_band", key, compute)


def _below_band_spline(m: Measurement, key: tuple, rows: np.ndarray) -> Resampler:
    """The interpolation of ``_band_limited``'s ``rows`` of the record, derived once per record and
    rows: a node's baseline is searched against every measurement, and the spline's prefilter was
    ~1.6 ms of a 36 ms ``assess``. A baseline keeps the spline's coefficients (as many numbers as
    the filtered traces), not the filtered traces too."""
    return m.derived("below_band_spline", (key, tuple(int(r) for r in rows)),
                     lambda: Resampler.of(_band_limited(m)[rows], m.t0_s, m.fs_hz))


def _in_band_energy(x: np.ndarray, m: Measurement) -> np.ndarray:
    """Energy of ``x`` [k, n_rows, n] matched-filtered with the excitation burst, one value per k.

    By Parseval, sum |X(f)|^2 |B(f)|^2 over the (zero-padded) spectrum: the correlation's energy
    without computing the correlation."""
    n_fft, gain = _burst_power(m.fs_hz, m.excitation_hz, m.cycles, x.shape[-1])
    power = np.abs(sp_fft.rfft(x, n_fft, axis=-1)) ** 2
    power[..., 1:] *= 2.0  # the one-sided spectrum's other half (DC and Nyquist counted twice: immaterial here)
    return np.einsum("krf,f->k", power, gain)


@functools.lru_cache(maxsize=16)
def _burst_power(fs_hz: float, excitation_hz: float, cycles: int, n: int) -> tuple[int, np.ndarray]:
    """(FFT length for ``n`` samples, |B(f)|^2 of the excitation burst at that length), per acquisition setup."""
    burst = hann_burst(fs_hz, excitation_hz, cycles)
    n_fft = sp_fft.next_fast_len(n + burst.size, real=True)
    gain = np.abs(sp_fft.rfft(burst, n_fft)) ** 2
    gain.flags.writeable = False
    return n_fft, gain


@functools.lru_cache(maxsize=16)
def _band_weight(fs_hz: float, excitation_hz: float, cycles: int, n: int) -> tuple[int, slice, np.ndarray]:
    """(FFT length, the bins where the burst's |B(f)|^2 exceeds 1e-8 of its peak, |B(f)|^2 there): the
    band a gain is judged in (189 of 3376 bins at 85 kHz, 5 cycles, 10 MHz, 6000 samples)."""
    n_fft, gain = _burst_power(fs_hz, excitation_hz, cycles, n)
    inside = np.flatnonzero(gain > 1e-8 * gain.max())
    band = slice(int(inside[0]), int(inside[-1]) + 1)
    weight = gain[band].copy()
    weight.flags.writeable = False
    return n_fft, band, weight


def _parabola_min(x: np.ndarray, y: np.ndarray) -> float:
    """Abscissa of the minimum of the parabola through the lowest sample and its neighbours."""
    k = int(np.argmin(y))
    if k == 0 or k == len(y) - 1:
        return float(x[k])
    y0, y1, y2 = y[k - 1], y[k], y[k + 1]
    curvature = y0 - 2 * y1 + y2
    if curvature <= 0:
        return float(x[k])
    return float(x[k] + 0.5 * (y0 - y2) / curvature * (x[1] - x[0]))


def select_baseline(
    library: Sequence[Measurement],
    current: Measurement,
    *,
    compensate: bool = True,
    max_stretch: float = DEFAULT_MAX_STRETCH,
    max_residual: float = DEFAULT_MAX_RESIDUAL,
    rx_mask: np.ndarray | None = None,
    shortlist: int | None = OBS_SHORTLIST,
) -> BaselineMatch | NoValidBaseline:
    """OBS (+ BSS when ``compensate``): the library entry that best explains ``current``, or abstain.

    Without compensation the entry with the smallest unstretched residual is chosen. Receivers
    where ``rx_mask`` is False are left out of the comparison. Entries
    incompatible with ``current`` (other geometry or sampling) are skipped; if none is
    compatible the result is NoValidBaseline naming the first mismatch.
    With compensation, only the ``shortlist`` entries of smallest unstretched residual (on every
    SEARCH_DECIMATION-th sample: microseconds each) get the stretch search (~6 ms each); the
    others too if none of those is valid. None: search every entry.
    """
    if len(library) == 0:
        raise CompensationError("the baseline library is empty")
    compatible, mismatch = [], None
    for i, baseline in enumerate(library):
        try:
            check_compatible(baseline, current)
        except BaselineMismatch as exc:
            mismatch = mismatch or str(exc)
            continue
        compatible.append(i)
    return select_compatible_baseline(library, compatible, current, compensate=compensate, max_stretch=max_stretch,
                                      max_residual=max_residual, rx_mask=rx_mask, shortlist=shortlist,
                                      mismatch=mismatch)


def select_compatible_baseline(
    library: Sequence[Measurement],
    compatible: Sequence[int],
    current: Measurement,
    *,
    compensate: bool = True,
    max_stretch: float = DEFAULT_MAX_STRETCH,
    max_residual: float = DEFAULT_MAX_RESIDUAL,
    rx_mask: np.ndarray | None = None,
    shortlist: int | None = OBS_SHORTLIST,
    mismatch: str | None = None,
    keep_best: bool = False,
    common_gain: bool = False,
) -> BaselineMatch | NoValidBaseline:
    """``select_baseline`` among the library entries ``compatible`` (indices already checked with
    ``check_compatible``); ``mismatch``: why the others are not, for the abstention. ``keep_best``:
    the best match even when it leaves more than ``max_residual`` (the caller judges it, with
    ``unexplained``); the search is the same either way. ``common_gain``: each entry is first
    scaled by its common gain where that explains the change (``common_gain_of``), so that a ring's
    drift buys no stretch; ``with_common_gain`` is the same after the stretch."""
    if len(library) == 0:
        raise CompensationError("the baseline library is empty")
    compatible = list(compatible)
    if not compatible:
        return NoValidBaseline(None, math.inf, max_residual, f"no compatible baseline: {mismatch}")
    rows = receiver_rows(current.n_rx, rx_mask)
    gains: dict[int, float] = {}
    entries: dict[int, Measurement] = {}

    def entry(i: int) -> Measurement:
        """Library entry ``i`` scaled by its common gain (computed once, for the entries searched)."""
        if i not in entries:
            gains[i] = common_gain_of(library[i], current, rx_mask) if common_gain else 1.0
            entries[i] = library[i] if gains[i] == 1.0 else scaled(library[i], gains[i])
        return entries[i]

    if not compensate:
        target = current.traces[rows].astype(np.float64)
        return _choose(entries, [(_relative_residual(target, entry(i).traces[rows].astype(np.float64)), i, 0.0,
                                  gains[i]) for i in compatible], {}, max_residual, keep_best)
    order = compatible
    if shortlist is not None and len(compatible) > shortlist:
        target = current.traces[rows, ::SEARCH_DECIMATION].astype(np.float64)
        plain = [_relative_residual(target, library[i].traces[rows, ::SEARCH_DECIMATION].astype(np.float64))
                 for i in compatible]
        order = [compatible[k] for k in np.argsort(plain, kind="stable")]
    candidates: list[tuple[float, int, float, float]] = []
    moved: dict[int, np.ndarray] = {}  # stretched traces of each searched entry
    for rank, i in enumerate(order):
        if shortlist is not None and rank == shortlist and min(c[0] for c in candidates) <= max_residual:
            break
        entry(i)  # its gain
        stretch, residual, moved[i] = _stretch_search(library[i], current, max_stretch=max_stretch, rx_mask=rx_mask,
                                                      gain=gains[i])
        candidates.append((residual, i, stretch, gains[i]))
    return _choose(entries, candidates, moved, max_residual, keep_best)


def common_gain_of(baseline: Measurement, current: Measurement, rx_mask: np.ndarray | None = None) -> float:
    """The one gain, common to the receivers ``rx_mask`` keeps, that best explains ``current`` from
    ``baseline`` in the excitation's band; 1.0 unless it removes at least MIN_GAIN_EXPLAINED of the
    residual's in-band energy and |ln gain| <= MAX_COMMON_GAIN_CHANGE.

    A ring whose gain or coupling drifts as a whole scales every arrival alike; against the unscaled
    baseline the map images that copy of the record as a scatterer at the Tx ring (full-wave dev set,
    16-ring, defect-free, noisy: peak DI 0.025 for 1 % less gain, 0.11 for 5 %; threshold 0.02). A
    defect lowers the coherent field too (its T(0,1) transmission loss) but also scatters new
    arrivals, so a gain explains at most 0.36 of a defect's in-band residual (every full-wave pair of
    the dev and own sets), and 0.78-1.0 of a 2-5 % drift's (0.41-0.44 for 1 % with absorbing ends and
    noise, where it images below the threshold anyway). Judged in band like the stretch: the record's
    noise above the band is no gain's. docs/imaging.md, "Common gain"."""
    rows = receiver_rows(current.n_rx, rx_mask)
    n_fft, band, weight = _band_weight(current.fs_hz, current.excitation_hz, current.cycles, current.n_samples)
    b = sp_fft.rfft(baseline.traces[rows], n_fft, axis=-1)[:, band].astype(np.complex128)  # float32 transform
    t = sp_fft.rfft(current.traces[rows], n_fft, axis=-1)[:, band].astype(np.complex128)
    bb = float(np.einsum("rf,f->", np.abs(b) ** 2, weight))
    tb = float(np.einsum("rf,f->", (t * b.conj()).real, weight))
    tt = float(np.einsum("rf,f->", np.abs(t) ** 2, weight))
    if not bb > 0:
        return 1.0
    gain = tb / bb
    if not (gain > 0 and abs(math.log(gain)) <= MAX_COMMON_GAIN_CHANGE):
        return 1.0
    plain = tt - 2.0 * tb + bb  # in-band energy of current - baseline, and of current - gain x baseline
    left = tt - gain * tb
    return gain if left <= (1.0 - MIN_GAIN_EXPLAINED) * plain else 1.0


def scaled(m: Measurement, gain: float) -> Measurement:
    """A copy of ``m`` with every trace times ``gain``."""
    return replace(m, traces=(m.traces.astype(np.float64) * gain).astype(np.float32))


def with_common_gain(match: BaselineMatch, current: Measurement, rx_mask: np.ndarray | None = None) -> BaselineMatch:
    """``match`` with its (stretched) baseline scaled by ``common_gain_of`` it, the residual recomputed
    (``match`` itself when that gain is 1): a drift found once the stretch is undone."""
    gain = common_gain_of(match.baseline, current, rx_mask)
    if gain == 1.0:
        return match
    rows = receiver_rows(current.n_rx, rx_mask)
    baseline = scaled(match.baseline, gain)
    residual = _relative_residual(current.traces[rows].astype(np.float64), baseline.traces[rows].astype(np.float64))
    return BaselineMatch(match.index, match.stretch, residual, baseline, match.gain * gain)


def as_recorded(library: Sequence[Measurement], index: int, current: Measurement,
                rx_mask: np.ndarray | None = None) -> BaselineMatch:
    """Library entry ``index`` as the match of ``current`` without any stretch (the receivers ``rx_mask``
    keeps give the residual): what is judged when the stretch the search found cannot be trusted."""
    return warmed_match(library, index, current, 0.0, rx_mask)


def thermometer_stretch(baseline: Measurement, current: Measurement) -> float | None:
    """The stretch the records' own temperatures predict, STRETCH_PER_DEGC per degC of warming; None
    when either record has no temperature."""
    change = current.temperature_c - baseline.temperature_c
    return STRETCH_PER_DEGC * change if math.isfinite(change) else None


def thermometer_offset_c(match: BaselineMatch, temperature_c: float | None) -> float | None:
    """How much further the thermometers say the pipe's temperature moved since the matched baseline than
    its stretch says (degC, STRETCH_PER_DEGC per degC); None without both temperatures. About 0 while
    sensor and wall agree: a drifting, stuck or misplaced sensor shows as a growing offset."""
    if temperature_c is None:
        return None
    change = float(temperature_c) - match.baseline.temperature_c
    return change - match.stretch / STRETCH_PER_DEGC if math.isfinite(change) else None


def disagrees_with_thermometers(stretch: float, predicted: float) -> bool:
    """Whether a stretch the search found is further from the thermometers' than they can be wrong by."""
    return abs(stretch - predicted) > THERMOMETER_TOLERANCE_C * STRETCH_PER_DEGC + THERMOMETER_RELATIVE * abs(predicted)


def at_thermometer_stretch(library: Sequence[Measurement], compatible: Sequence[int], current: Measurement,
                           rx_mask: np.ndarray | None = None) -> BaselineMatch | None:
    """The compatible library entry nearest ``current`` in temperature, warmed by the stretch the two
    temperatures predict (``warmed_match``); None when no compatible entry has a temperature or
    ``current`` has none."""
    known = [(abs(current.temperature_c - library[i].temperature_c), i, stretch) for i in compatible
             if (stretch := thermometer_stretch(library[i], current)) is not None]
    if not known:
        return None
    _, index, stretch = min(known)
    return warmed_match(library, index, current, stretch, rx_mask)


def warmed_match(library: Sequence[Measurement], index: int, current: Measurement, stretch: float,
                 rx_mask: np.ndarray | None = None) -> BaselineMatch:
    """Library entry ``index`` warmed by ``stretch`` (the medium's response stretched, imaging/thermal.py)
    as the match of ``current``, the receivers ``rx_mask`` keeps giving the residual; where the entry
    has no sample the current is its own reference, as in the search."""
    entry = library[index]
    if stretch != 0.0:  # else the entry itself, with what has been derived from it
        at = _sample_times_s(current) / (1.0 + stretch)
        traces = _own_reference_where_unrecorded(stretch_traces(entry, stretch), at, entry, current)
        entry = replace(entry, traces=traces.astype(np.float32))
    rows = receiver_rows(current.n_rx, rx_mask)
    residual = _relative_residual(current.traces[rows].astype(np.float64), entry.traces[rows].astype(np.float64))
    return BaselineMatch(index, stretch, residual, entry)


def unexplained(match: BaselineMatch, max_residual: float, why: str = "") -> NoValidBaseline:
    """The abstention for a best ``match`` that leaves more than ``max_residual`` of the record's
    energy unexplained; ``why``: what else was weighed (appended to the reason)."""
    return NoValidBaseline(
        match.index, match.residual, max_residual,
        f"best baseline leaves {match.residual:.3g} of the signal energy unexplained (limit {max_residual:.3g})"
        + (f"; {why}" if why else ""),
    )


def _choose(entries: Mapping[int, Measurement], candidates: list[tuple[float, int, float, float]],
            moved: dict[int, np.ndarray], max_residual: float, keep_best: bool = False) -> BaselineMatch | NoValidBaseline:
    """The best (residual, index, stretch, gain) candidate as a match, or the abstention; ``entries``: the
    library entries by index, as searched (scaled by their gain)."""
    # Among near-equal matches prefer the least stretch: the closest temperature also matches
    # what a stretch cannot model (amplitude, mode shape changes with temperature).
    lowest = min(c[0] for c in candidates)
    ties = [c for c in candidates if c[0] <= lowest * (1.0 + TIE_TOLERANCE)]
    residual, index, stretch, gain = min(ties, key=lambda c: (abs(c[2]), c[0]))
    chosen = entries[index] if stretch == 0.0 else replace(entries[index], traces=moved[index])
    match = BaselineMatch(index, stretch, residual, chosen, gain)
    if not residual <= max_residual and not keep_best:
        return unexplained(match, max_residual)
    return match

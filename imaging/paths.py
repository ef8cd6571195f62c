"""Every way a scattered T(0,1) wave can travel from the Tx ring, via a point on the wall, to a receiver.

Unrolled wall: ``z`` axial mm from the Tx ring (the Rx ring at ``D = tx_rx_distance_mm``), ``s``
round the circumference (periodic). The Tx ring launches an axisymmetric plane wave both ways;
a pipe end reflects it (image method), so a point at z is hit by

- the direct wave, after |z|;
- the wave reflected at the near end (behind the Tx ring, at ``-A``), after 2A + z;
- the wave reflected at the far end (beyond the Rx ring, at ``F``), after 2F - z.

The point re-radiates a cylindrical wave; it reaches receiver m directly, or after reflecting
at the far end (image of the Rx ring at 2F - D) or the near end (image at -2A - D), each
either way round the pipe (two wraps; the echo fit of imaging/multidefect.py follows it further,
once more round either way per two wraps more: the scattered wave keeps circling the pipe within
the record). Expected amplitude of a path, per unit scatterer
strength: the ends' reflection coefficients, 2-D spreading sqrt(lambda / r) (softened within
half a wavelength), and, for torsional (circumferentially polarised) receivers, |cos| of the
arrival direction from the pipe axis: an SH wave arriving at angle phi moves the wall
circumferentially by cos(phi).

A sparse Tx ring (``PathModel.tx_arcs_mm`` set): the plane wave above is only the ring's
circumferential order 0. N elements launch orders 0, N, 2N, ...; order N propagates once the
excitation band reaches its cut-off N c / C (8 elements on the paper's pipe: 72.1 kHz on its
347.5 mm mid-wall, 69.6 kHz on a 360 mm one, inside a 75 kHz burst's band) and, near cut-off, carries more of the incident field than order 0
(its excitation grows as k / k_z). The incident wave is then modelled as what it is in the
wall: a cylindrical wave from every element and from its images one, two, ... circumferences
round (``tx_images`` either way), each with the same spreading and polarisation as a scattered
path and the spacing C / N over lambda as its weight (the elements' sum is then the plane wave
of amplitude 1 far from the ring, by stationary phase). Every path of a family and way round
then has one such incident term per element image, all in the same coherence group.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

MAX_WRAPS = 16  # the legs a path model may follow round the pipe (8 turns either way)
NEGLIGIBLE_WEIGHT = 1e-12  # an incident term this weak (a pixel on the Tx ring, off every element) counts nothing


class PathModelError(ValueError):
    """A path model's geometry is inconsistent (e.g. an end between the rings)."""


@dataclass(frozen=True)
class PathFamily:
    """Incident length |in_offset_mm + in_sign * z|; outgoing from z to the Rx image at ``rx_image_mm``.

    ``factor`` is the product of the end reflection coefficients met on the way.
    """

    name: str
    in_offset_mm: float
    in_sign: float
    rx_image_mm: float
    factor: float


@dataclass(frozen=True)
class PathModel:
    """Geometry and amplitude model of the scattered paths (hashable: it keys the gather-table cache).

    ``circumference_mm`` is the wrap length the scattered wave travels round the pipe (the
    mid-wall circumference when the wall thickness is known). ``near_end_mm``/``far_end_mm``
    are the pipe ends' axial positions from the Tx ring (None: unknown, not modelled).
    ``wraps`` 1 keeps only the shorter way round, 2 both, 3 and 4 also one more turn round the
    pipe the shorter and the other way, and so on (``wrap_turns``). Paths whose end-reflection factor is
    below ``min_factor`` are dropped (e.g. every end path of a pipe with absorbing ends).
    ``tx_arcs_mm``: the Tx elements' positions round the wrap circumference (mm from angle 0)
    when the incident wave is modelled element by element (module docstring), with
    ``tx_images`` images of each either way; empty: the axisymmetric plane wave.
    """

    tx_rx_distance_mm: float
    circumference_mm: float
    wavelength_mm: float
    near_end_mm: float | None = None
    far_end_mm: float | None = None
    near_reflection: float = 0.0
    far_reflection: float = 0.0
    polarization: bool = True
    wraps: int = 2
    min_factor: float = 0.05
    tx_arcs_mm: tuple[float, ...] = ()
    tx_images: int = 3

    def __post_init__(self) -> None:
        if not (self.tx_rx_distance_mm > 0 and self.circumference_mm > 0 and self.wavelength_mm > 0):
            raise PathModelError("distances and wavelength must be positive")
        if not 1 <= self.wraps <= MAX_WRAPS:
            raise PathModelError(f"wraps must be 1 to {MAX_WRAPS}, got {self.wraps}")
        if self.tx_images < 0:
            raise PathModelError(f"tx_images must be >= 0, got {self.tx_images}")
        if not all(math.isfinite(a) for a in self.tx_arcs_mm):
            raise PathModelError("tx_arcs_mm must be finite")
        if self.near_end_mm is not None and self.near_end_mm > 0:
            raise PathModelError("the near end lies behind the Tx ring (near_end_mm <= 0)")
        if self.far_end_mm is not None and self.far_end_mm < self.tx_rx_distance_mm:
            raise PathModelError("the far end lies beyond the Rx ring (far_end_mm >= tx_rx_distance_mm)")

    def families(self) -> tuple[PathFamily, ...]:
        """The incident x outgoing combinations kept by this model, direct-direct first."""
        d = self.tx_rx_distance_mm
        incident = [("direct", 0.0, 1.0, 1.0)]
        outgoing = [("direct", d, 1.0)]
        if self.near_end_mm is not None:
            incident.append(("near", -2.0 * self.near_end_mm, 1.0, self.near_reflection))
            outgoing.append(("near", 2.0 * self.near_end_mm - d, self.near_reflection))
        if self.far_end_mm is not None:
            incident.append(("far", 2.0 * self.far_end_mm, -1.0, self.far_reflection))
            outgoing.append(("far", 2.0 * self.far_end_mm - d, self.far_reflection))
        out = []
        for in_name, offset, sign, r_in in incident:
            for out_name, image, r_out in outgoing:
                factor = r_in * r_out
                if factor >= self.min_factor:
                    out.append(PathFamily(f"{in_name}>{out_name}", offset, sign, image, factor))
        return tuple(out)

    @property
    def elements(self) -> bool:
        """True when the incident wave is modelled element by element (a sparse Tx ring)."""
        return bool(self.tx_arcs_mm)


def ring_order_cutoff_hz(n_elements: int, circumference_mm: float, velocity_m_s: float) -> float:
    """Cut-off of a ring's first circumferential order above 0, N c / C: below it only order 0 propagates."""
    return n_elements * velocity_m_s * 1000.0 / circumference_mm


def sparse_ring(n_elements: int, circumference_mm: float, velocity_m_s: float, excitation_hz: float,
                cycles: int) -> bool:
    """Does a ring of ``n_elements`` launch more than order 0 into the wall? True when order N's
    cut-off lies below the upper edge of the burst's main lobe, f (1 + 2 / cycles) (a Hann burst)."""
    if n_elements < 1:
        return False
    return ring_order_cutoff_hz(n_elements, circumference_mm, velocity_m_s) < excitation_hz * (1.0 + 2.0 / cycles)


def _element_incident(model: PathModel, zeta: np.ndarray, pixel_arc_mm: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(length_mm, weight) [E, *broadcast shape] of the cylindrical wave from every Tx element image (element-major,
    then image -tx_images..tx_images) at pixels ``zeta`` mm along the axis from the (imaged) ring, at ``pixel_arc_mm``
    round the pipe from angle 0."""
    circ = model.circumference_mm
    zeta = np.asarray(zeta, dtype=np.float64)
    s = _element_arcs(model, pixel_arc_mm, len(np.broadcast_shapes(zeta.shape, np.shape(pixel_arc_mm))))
    r = np.sqrt(np.square(zeta)[None] + np.square(s))
    w = path_weight(circ / len(model.tx_arcs_mm) / model.wavelength_mm, zeta[None], r, model)
    return r, np.where(w < NEGLIGIBLE_WEIGHT, 0.0, w)


def _element_arcs(model: PathModel, pixel_arc_mm: np.ndarray, ndim: int) -> np.ndarray:
    """[E, ...]: the signed arc (mm) from every Tx element image to pixels ``pixel_arc_mm`` round the pipe
    (``ndim`` the pixels' broadcast dimensions)."""
    circ = model.circumference_mm
    images = np.arange(-model.tx_images, model.tx_images + 1) * circ
    tx = np.repeat(np.asarray(model.tx_arcs_mm, dtype=np.float64), images.size)
    shift = np.tile(images, len(model.tx_arcs_mm))
    extra = (1,) * ndim
    base = signed_arc_mm((np.asarray(pixel_arc_mm, dtype=np.float64)[None] - tx.reshape((-1,) + extra))
                         * (360.0 / circ), circ)
    return base + shift.reshape((-1,) + extra)


def element_scattering_cosines(model: PathModel, axial_mm: np.ndarray, rel_angle_deg: np.ndarray,
                               rx_angle_deg: float | np.ndarray = 0.0,
                               arc_offset_mm: float | np.ndarray = 0.0) -> np.ndarray:
    """cos psi [P, *broadcast shape] of every path of ``stacked_paths`` (a model with Tx elements, same
    order, ``arc_offset_mm`` alike): psi the scattering angle at the pixel, between the incident wave's
    direction there (the gradient of the incident length) and the way out to the receiver (minus the
    gradient of the outgoing one), on the unrolled wall, end images unfolded."""
    legs = _element_legs(model, axial_mm, rel_angle_deg, rx_angle_deg, arc_offset_mm)
    if legs is None:
        return np.zeros((0,) + np.broadcast_shapes(_pixels_shape(axial_mm, rel_angle_deg, rx_angle_deg),
                                                   np.shape(arc_offset_mm)))
    s = _element_arcs(model, legs.pixel_arc, len(legs.shape))  # [E, ...]
    r_in = np.sqrt(np.square(legs.zeta)[:, None] + np.square(s)[None])  # [F, E, ...]
    along = (legs.sign * legs.zeta * legs.dz)[:, None, None]  # [F, 1, 1, ...]
    round_ = -(s[None, None] * legs.legs[None, :, None])  # [1, W, E, ...]
    cos_psi = (along + round_) / (r_in[:, None] * legs.r_out[:, :, None])  # [F, W, E, ...]
    return np.where(np.isfinite(cos_psi), cos_psi, 1.0).reshape((-1,) + legs.shape)


def incident_terms(model: PathModel, axial_mm: np.ndarray, pixel_arc_mm: np.ndarray,
                   family: PathFamily) -> list[tuple[np.ndarray, np.ndarray]]:
    """(length_mm, weight) of each incident term of ``family`` at pixels (axial, arc round the pipe from angle 0):
    the plane wave (one term of weight 1), or one cylindrical wave per Tx element image."""
    zeta = family.in_offset_mm + family.in_sign * np.asarray(axial_mm, dtype=np.float64)
    if not model.elements:
        return [(np.abs(zeta), np.ones(np.shape(zeta)))]
    lengths, weights = _element_incident(model, zeta, pixel_arc_mm)
    return list(zip(lengths, weights, strict=True))


def coherence_groups(model: PathModel) -> int:
    """Number of groups summed coherently: one per path family and way round the pipe.

    A defect's scattered phase depends on the direction it radiates in (forward, back, or
    round the pipe one way or the other), so only paths leaving it in the same kind of
    direction are added with their phase; the groups are then added in power.
    """
    return len(model.families()) * model.wraps


def signed_arc_mm(rel_angle_deg: np.ndarray, circumference_mm: float) -> np.ndarray:
    """Signed circumferential offset in (-C/2, C/2] for an angle difference in degrees."""
    wrapped = np.mod(np.asarray(rel_angle_deg, dtype=np.float64) + 180.0, 360.0) - 180.0
    wrapped = np.where(wrapped == -180.0, 180.0, wrapped)
    return wrapped * (circumference_mm / 360.0)


def wrap_turns(wrap: int) -> int:
    """Whole turns round the pipe added to the shorter way's arc on leg ``wrap``, counted in the
    arc's own direction: 0 (the shorter way), -1 (the other way), +1, -2, +2, ..."""
    turns = (wrap + 1) // 2
    return -turns if wrap % 2 else turns


def wrap_offsets_mm(arc_mm: np.ndarray, circumference_mm: float, wraps: int) -> list[np.ndarray]:
    """The circumferential legs to take: the shorter way round, (wraps >= 2) the other way, then
    each once more round the pipe, and so on (``wrap_turns``); ``arc_mm`` the shorter way's."""
    direction = np.where(arc_mm >= 0, 1.0, -1.0) * circumference_mm
    return [arc_mm + wrap_turns(k) * direction if k else arc_mm for k in range(wraps)]


def path_weight(factor: float | np.ndarray, dz_mm: np.ndarray, r_mm: np.ndarray, model: PathModel) -> np.ndarray:
    """Expected amplitude per unit strength: factor * sqrt(lambda / max(r, lambda/2)) * |cos(arrival)|."""
    lam = model.wavelength_mm
    w = factor * np.sqrt(lam / np.maximum(r_mm, 0.5 * lam))
    if model.polarization:
        w = w * np.where(r_mm > 0, np.abs(dz_mm) / np.where(r_mm > 0, r_mm, 1.0), 1.0)
    return w


def scatter_paths(
    model: PathModel, axial_mm: np.ndarray, rel_angle_deg: np.ndarray, rx_angle_deg: float | np.ndarray = 0.0
) -> list[tuple[int, np.ndarray, np.ndarray]]:
    """(coherence group, length_mm, weight) of every modelled path, broadcast over axial_mm x rel_angle_deg.

    ``rel_angle_deg`` is the pixel angle minus the receiver angle ``rx_angle_deg`` (which only
    an element-by-element incident wave needs). The group is ``family_index * wraps + wrap``
    (see ``coherence_groups``); with Tx elements a group holds one path per element image.
    """
    z = np.asarray(axial_mm, dtype=np.float64)
    arc = signed_arc_mm(rel_angle_deg, model.circumference_mm)
    pixel_arc = (np.asarray(rel_angle_deg, dtype=np.float64) + rx_angle_deg) * (model.circumference_mm / 360.0)
    paths = []
    for f, fam in enumerate(model.families()):
        incident = incident_terms(model, z, pixel_arc, fam)
        dz = fam.rx_image_mm - z
        for wrap, leg in enumerate(wrap_offsets_mm(arc, model.circumference_mm, model.wraps)):
            r = np.hypot(dz, leg)
            out = path_weight(fam.factor, dz, r, model)
            for in_length, in_weight in incident:
                length, weight = np.broadcast_arrays(in_length + r, out if not model.elements else in_weight * out)
                paths.append((f * model.wraps + wrap, length, weight))
    return paths


def stacked_paths(
    model: PathModel, axial_mm: np.ndarray, rel_angle_deg: np.ndarray, rx_angle_deg: float | np.ndarray = 0.0,
    arc_offset_mm: float | np.ndarray = 0.0,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``scatter_paths`` as three arrays: groups [P] (int64), length_mm and weight [P, *broadcast shape].

    The same arithmetic, done once for all families and wraps (few large array operations
    instead of many small ones: what a small grid needs). With Tx elements the same paths in
    the same order, families x wraps x element images (a group then repeats).

    ``arc_offset_mm`` (broadcast like the pixels): the paths of a point that far round the pipe from each
    pixel, along the *pixel's* legs (each leg, and so each group, keeps its way and turns round the pipe
    where the point's own shorter way would be the other): the parts of an extended scatterer
    (imaging/echofit.py ``group_waves``) share their centre's groups.
    """
    if model.elements:
        return _stacked_element_paths(model, axial_mm, rel_angle_deg, rx_angle_deg, arc_offset_mm)
    families = model.families()
    if not families:
        shape = np.broadcast_shapes(np.shape(axial_mm), np.shape(rel_angle_deg), np.shape(arc_offset_mm))
        return np.zeros(0, np.int64), np.zeros((0,) + shape), np.zeros((0,) + shape)
    z = np.asarray(axial_mm, dtype=np.float64)
    arc = signed_arc_mm(rel_angle_deg, model.circumference_mm)
    legs = np.stack(np.broadcast_arrays(*(leg + arc_offset_mm for leg in
                                          wrap_offsets_mm(arc, model.circumference_mm, model.wraps))))  # [W, ...]
    extra = (1,) * max(z.ndim, legs.ndim - 1)
    offset, sign, image, factor = (np.array([getattr(f, name) for f in families]).reshape((-1, 1) + extra)
                                   for name in ("in_offset_mm", "in_sign", "rx_image_mm", "factor"))
    incident = np.abs(offset + sign * z)  # [F, 1, ...]
    dz = image - z
    # sqrt of the sum of squares, not np.hypot (~20x slower here); lengths are mm, far from overflow.
    r = np.sqrt(np.square(dz) + np.square(legs[None]))  # [F, W, ...]
    length = incident + r
    weight = path_weight(factor, dz, r, model)
    length, weight = np.broadcast_arrays(length, weight)
    n = len(families) * model.wraps
    groups = np.arange(n, dtype=np.int64)
    return groups, length.reshape((n,) + length.shape[2:]), weight.reshape((n,) + weight.shape[2:])


def _scalar_arc(angle_deg: float, circ: float) -> float:
    diff = (angle_deg + 180.0) % 360.0 - 180.0
    if diff == -180.0:
        diff = 180.0
    return diff * circ / 360.0


def _scalar_weight(factor: float, axial: float, r: float, model: PathModel) -> float:
    lam = model.wavelength_mm
    w = factor * math.sqrt(lam / max(r, 0.5 * lam))
    if model.polarization and r > 0:
        w *= abs(axial) / r
    return w


@dataclass(frozen=True)
class _ElementLegs:
    """What every path of a model with Tx elements shares at a set of pixels: the broadcast ``shape``,
    each pixel's arc round the pipe from angle 0, the circumferential ``legs`` [W, ...] to the
    receiver, and per family [F, ...] the unfolded incident distance ``zeta``, its ``sign``, the
    end-echo ``factor``, the axial distance ``dz`` to the receiver's image and the outgoing lengths
    ``r_out`` [F, W, ...]."""

    shape: tuple[int, ...]
    pixel_arc: np.ndarray
    legs: np.ndarray
    sign: np.ndarray
    factor: np.ndarray
    zeta: np.ndarray
    dz: np.ndarray
    r_out: np.ndarray


def _pixels_shape(axial_mm: np.ndarray, rel_angle_deg: np.ndarray, rx_angle_deg: float | np.ndarray) -> tuple:
    return np.broadcast_shapes(np.shape(axial_mm), np.shape(rel_angle_deg), np.shape(rx_angle_deg))


def _element_legs(model: PathModel, axial_mm: np.ndarray, rel_angle_deg: np.ndarray,
                  rx_angle_deg: float | np.ndarray, arc_offset_mm: float | np.ndarray = 0.0) -> _ElementLegs | None:
    """The shared geometry of ``_stacked_element_paths`` and ``element_scattering_cosines`` (None: no families;
    ``arc_offset_mm`` as ``stacked_paths``)."""
    families = model.families()
    if not families:
        return None
    shape = np.broadcast_shapes(_pixels_shape(axial_mm, rel_angle_deg, rx_angle_deg), np.shape(arc_offset_mm))
    circ = model.circumference_mm
    z = np.broadcast_to(np.asarray(axial_mm, dtype=np.float64), shape)
    rel = np.broadcast_to(np.asarray(rel_angle_deg, dtype=np.float64), shape)
    offset_mm = np.broadcast_to(np.asarray(arc_offset_mm, dtype=np.float64), shape)
    legs = np.stack(np.broadcast_arrays(*(leg + offset_mm for leg in
                                          wrap_offsets_mm(signed_arc_mm(rel, circ), circ, model.wraps))))  # [W, ...]
    extra = (1,) * len(shape)
    offset, sign, image, factor = (np.array([getattr(f, name) for f in families]).reshape((-1,) + extra)
                                   for name in ("in_offset_mm", "in_sign", "rx_image_mm", "factor"))
    dz = image - z[None]  # [F, ...]
    return _ElementLegs(shape, (rel + rx_angle_deg) * (circ / 360.0) + offset_mm, legs, sign, factor,
                        offset + sign * z[None], dz, np.hypot(dz[:, None], legs[None]))


def _stacked_element_paths(
    model: PathModel, axial_mm: np.ndarray, rel_angle_deg: np.ndarray, rx_angle_deg: float | np.ndarray,
    arc_offset_mm: float | np.ndarray = 0.0,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``stacked_paths`` of a model with Tx elements: families x wraps x element images, in ``scatter_paths``' order."""
    legs = _element_legs(model, axial_mm, rel_angle_deg, rx_angle_deg, arc_offset_mm)
    if legs is None:
        shape = np.broadcast_shapes(_pixels_shape(axial_mm, rel_angle_deg, rx_angle_deg), np.shape(arc_offset_mm))
        return np.zeros(0, np.int64), np.zeros((0,) + shape), np.zeros((0,) + shape)
    r_in, w_in = (np.moveaxis(a, 0, 1) for a in _element_incident(model, legs.zeta, legs.pixel_arc))  # [F, E, ...]
    w_out = path_weight(legs.factor[:, None], legs.dz[:, None], legs.r_out, model)
    length = r_in[:, None] + legs.r_out[:, :, None]  # [F, W, E, ...]
    weight = w_in[:, None] * w_out[:, :, None]
    n_f, n_w, n_e = legs.zeta.shape[0], model.wraps, r_in.shape[1]
    groups = np.repeat(np.arange(n_f * n_w, dtype=np.int64), n_e)
    return groups, length.reshape((-1,) + legs.shape), weight.reshape((-1,) + legs.shape)


def scalar_paths(model: PathModel, z_mm: float, rel_angle_deg: float,
                 rx_angle_deg: float = 0.0) -> list[tuple[int, float, float]]:
    """The same paths for one pixel, written out with scalar math (the literal oracle's model)."""
    circ = model.circumference_mm
    arc = _scalar_arc(rel_angle_deg, circ)
    direction = (1.0 if arc >= 0 else -1.0) * circ
    legs = [arc + wrap_turns(k) * direction for k in range(model.wraps)]
    pixel_deg = rel_angle_deg + rx_angle_deg
    out = []
    for f, fam in enumerate(model.families()):
        zeta = fam.in_offset_mm + fam.in_sign * z_mm
        if model.elements:
            scale = circ / len(model.tx_arcs_mm) / model.wavelength_mm
            incident = []
            for tx_arc in model.tx_arcs_mm:
                base = _scalar_arc(pixel_deg - tx_arc * 360.0 / circ, circ)
                for image in range(-model.tx_images, model.tx_images + 1):
                    r_in = math.hypot(zeta, base + image * circ)
                    w_in = _scalar_weight(scale, zeta, r_in, model)
                    incident.append((r_in, 0.0 if w_in < NEGLIGIBLE_WEIGHT else w_in))
        else:
            incident = [(abs(zeta), 1.0)]
        dz = fam.rx_image_mm - z_mm
        for wrap, leg in enumerate(legs):
            r = math.hypot(dz, leg)
            w = _scalar_weight(fam.factor, dz, r, model)
            for in_length, in_weight in incident:
                out.append((f * model.wraps + wrap, in_length + r, w * in_weight if model.elements else w))
    return out

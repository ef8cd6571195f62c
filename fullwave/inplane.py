"""The in-plane (plane-stress membrane) model: both wall motions, SH0 and S0, and conversion between them.

    m dv_z/dt = dN_zz/dz + dN_zs/ds + f_z,     m dv_s/dt = dN_zs/dz + dN_ss/ds + f_s,
    dN_zz/dt = h (A dv_z/dz + B dv_s/ds),      dN_ss/dt = h (B dv_z/dz + A dv_s/ds),
    dN_zs/dt = mu h (dv_z/ds + dv_s/dz),       A = E / (1 - nu^2),  B = nu A,

v the axial and circumferential velocities of the wall, N the membrane forces per unit length,
m = rho h + added areal mass. It carries the shear wave SH0 = T(0,1) (c_T = sqrt(mu / rho),
3130 m/s) and the plate's longitudinal wave S0 = L(0,2) at low frequency (c_P =
sqrt(A / rho), 5290 m/s), with the true polarisation of both in every direction, and converts
between them wherever the wall changes (a notch's edges, a mass).

Staggered grid (Virieux 1986) on the SH model's cells: v_s at cell centres in z and half a cell
on in s (j + 1/2); v_z on the faces between cells in z; N_zz, N_ss at cell centres; N_zs on the
faces, at j + 1/2. The pipe's ends are faces: N_zs = 0 there and the end faces' v_z carry half a
cell's mass (the wall stops at the face: a traction-free end, first-order exact for a plane
face). Face stiffness mu h is the harmonic mean of the four cells around a shear node (0 at the
ends), masses the mean of the two cells a velocity sits between. Stable for
c_P dt sqrt(1/dz^2 + 1/ds^2) <= 1, so it takes ~1.7 times as many steps as the SH model.

Two implementations of one step: ``step_numpy`` (the reference) and a fused numba loop (``run``).
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from fullwave.absorber import Cpml
from fullwave.compiled import jit, kernel_array
from fullwave.medium import Medium, harmonic_mean
from fullwave.transducers import PatchWeights, RingLayout, averaging_weights, rx_weights, tx_weights


@dataclass(frozen=True)
class InplaneOperator:
    """Update coefficients, already multiplied by dt (faces: [nz + 1, ns], cells: [nz, ns])."""

    dt_over_mass_z: np.ndarray  # at v_z (faces, j)
    dt_over_mass_s: np.ndarray  # at v_s (cells, j + 1/2)
    a_h: np.ndarray  # dt h E / (1 - nu^2) at cells
    b_h: np.ndarray  # dt h nu E / (1 - nu^2) at cells
    g_h: np.ndarray  # dt mu h at (faces, j + 1/2), 0 on the outer faces
    inv_dz: float
    inv_ds: float
    cpml: Cpml
    dt_s: float


@dataclass
class InplaneState:
    """Velocities at step n - 1/2, forces at step n, and the absorbing layer's memory variables."""

    vz: np.ndarray  # [nz + 1, ns]
    vs: np.ndarray  # [nz, ns]
    nzz: np.ndarray  # [nz, ns]
    nss: np.ndarray  # [nz, ns]
    nzs: np.ndarray  # [nz + 1, ns]
    psi_vz: np.ndarray  # d N_zz / dz at v_z
    psi_vs: np.ndarray  # d N_zs / dz at v_s
    psi_n: np.ndarray  # d v_z / dz at the normal forces
    psi_zs: np.ndarray  # d v_s / dz at N_zs
    step: int = 0

    @classmethod
    def zeros(cls, nz: int, ns: int, dtype: type = np.float32) -> InplaneState:
        face, cell = (nz + 1, ns), (nz, ns)
        return cls(vz=np.zeros(face, dtype), vs=np.zeros(cell, dtype), nzz=np.zeros(cell, dtype),
                   nss=np.zeros(cell, dtype), nzs=np.zeros(face, dtype), psi_vz=np.zeros(face, dtype),
                   psi_vs=np.zeros(cell, dtype), psi_n=np.zeros(cell, dtype), psi_zs=np.zeros(face, dtype))

    def copy(self) -> InplaneState:
        return dataclasses.replace(self, **{f.name: getattr(self, f.name).copy() for f in dataclasses.fields(self)
                                            if f.name != "step"})


def inplane_operator(medium: Medium, dt_s: float, cpml: Cpml, dtype: type = np.float32) -> InplaneOperator:
    grid = medium.grid
    mass, h = medium.areal_mass_kg_m2, medium.thickness_m
    mass_z = np.zeros((grid.nz + 1, grid.ns))
    mass_z[:-1] += mass / 2
    mass_z[1:] += mass / 2  # the end faces keep half a cell's mass: the wall stops there
    mass_s = (mass + np.roll(mass, -1, axis=1)) / 2
    stiffness = medium.youngs_modulus_pa / (1 - medium.poisson_ratio**2)
    mu_h = medium.shear_modulus_pa * h
    around = harmonic_mean(mu_h, np.roll(mu_h, -1, axis=1))  # cells j and j + 1
    g = np.zeros((grid.nz + 1, grid.ns))
    g[1:-1] = harmonic_mean(around[:-1], around[1:])  # and i - 1, i: the four cells round a shear node
    return InplaneOperator(kernel_array(dt_s / mass_z, dtype), kernel_array(dt_s / mass_s, dtype),
                           kernel_array(dt_s * stiffness * h, dtype),
                           kernel_array(dt_s * medium.poisson_ratio * stiffness * h, dtype),
                           kernel_array(dt_s * g, dtype), 1.0 / grid.dz_m, 1.0 / grid.ds_m, cpml.astype(dtype), dt_s)


def step_numpy(op: InplaneOperator, state: InplaneState, force_z: np.ndarray, force_s: np.ndarray) -> None:
    """One leapfrog step in place; ``force_z`` [nz + 1, ns] and ``force_s`` [nz, ns] in Pa at step n."""
    p, dz, ds = op.cpml, op.inv_dz, op.inv_ds
    st = state
    nzz_padded = np.concatenate([np.zeros_like(st.nzz[:1]), st.nzz, np.zeros_like(st.nzz[:1])])
    d_nzz = (nzz_padded[1:] - nzz_padded[:-1]) * dz  # at the faces; no force beyond the ends
    st.psi_vz[:] = p.b_face[:, None] * st.psi_vz + p.a_face[:, None] * d_nzz
    st.vz += op.dt_over_mass_z * (d_nzz + st.psi_vz + (st.nzs - np.roll(st.nzs, 1, axis=1)) * ds + force_z)
    d_nzs = (st.nzs[1:] - st.nzs[:-1]) * dz
    st.psi_vs[:] = p.b_cell[:, None] * st.psi_vs + p.a_cell[:, None] * d_nzs
    st.vs += op.dt_over_mass_s * (d_nzs + st.psi_vs + (np.roll(st.nss, -1, axis=1) - st.nss) * ds + force_s)
    d_vz = (st.vz[1:] - st.vz[:-1]) * dz
    st.psi_n[:] = p.b_cell[:, None] * st.psi_n + p.a_cell[:, None] * d_vz
    d_vz = d_vz + st.psi_n
    d_vs = (st.vs - np.roll(st.vs, 1, axis=1)) * ds
    st.nzz += op.a_h * d_vz + op.b_h * d_vs
    st.nss += op.b_h * d_vz + op.a_h * d_vs
    dvs_dz = (st.vs[1:] - st.vs[:-1]) * dz
    psi = st.psi_zs[1:-1]
    psi[:] = p.b_face[1:-1, None] * psi + p.a_face[1:-1, None] * dvs_dz
    dvz_ds = (np.roll(st.vz, -1, axis=1) - st.vz) * ds
    st.nzs[1:-1] += op.g_h[1:-1] * (dvz_ds[1:-1] + dvs_dz + psi)
    st.step += 1


def _memory(psi, row, b, a, d, ns):  # pragma: no cover - numba
    """CPML: psi = b psi + a d, and d += psi, for one row (skipped outside the layers)."""
    if a != 0.0 or b != 0.0:
        for j in range(ns):
            p = b * psi[row, j] + a * d[j]
            psi[row, j] = p
            d[j] += p


def _run_loops(mz, ms, a_h, b_h, g_h, inv_dz, inv_ds, a_c, b_c, a_f, b_f, vz, vs, nzz, nss, nzs, psi_vz, psi_vs,
               psi_n, psi_zs, amp_z, amp_s, zptr, zcol, zw, sptr, scol, sw, rxz_index, rxz_weight, rxz_owner,
               rxs_index, rxs_weight, rxs_owner, out):  # pragma: no cover - numba
    # Row pipeline per step: at row i, the velocities of face i and cell i, then the forces that
    # need only velocities up to row i (N_zs on face i, the normal forces of cell i - 1).
    nz, ns = vs.shape
    vzf = vz.reshape((nz + 1) * ns)
    vsf = vs.reshape(nz * ns)
    d = np.empty(ns, dtype=vs.dtype)
    e = np.empty(ns, dtype=vs.dtype)
    memory = _memory_compiled
    for n in range(amp_z.shape[0]):
        az, a_s = amp_z[n], amp_s[n]
        for i in range(nz + 1):
            # v_z on face i: dN_zz/dz (no force beyond the ends) + dN_zs/ds
            if i == 0:
                for j in range(ns):
                    d[j] = nzz[0, j] * inv_dz
            elif i == nz:
                for j in range(ns):
                    d[j] = -nzz[nz - 1, j] * inv_dz
            else:
                for j in range(ns):
                    d[j] = (nzz[i, j] - nzz[i - 1, j]) * inv_dz
            memory(psi_vz, i, b_f[i], a_f[i], d, ns)
            vz[i, 0] += mz[i, 0] * (d[0] + (nzs[i, 0] - nzs[i, ns - 1]) * inv_ds)
            for j in range(1, ns):
                vz[i, j] += mz[i, j] * (d[j] + (nzs[i, j] - nzs[i, j - 1]) * inv_ds)
            for k in range(zptr[i], zptr[i + 1]):
                c = zcol[k]
                vz[i, c] += mz[i, c] * az * zw[k]
            # v_s in cell i: dN_zs/dz + dN_ss/ds
            if i < nz:
                for j in range(ns):
                    d[j] = (nzs[i + 1, j] - nzs[i, j]) * inv_dz
                memory(psi_vs, i, b_c[i], a_c[i], d, ns)
                for j in range(ns - 1):
                    vs[i, j] += ms[i, j] * (d[j] + (nss[i, j + 1] - nss[i, j]) * inv_ds)
                vs[i, ns - 1] += ms[i, ns - 1] * (d[ns - 1] + (nss[i, 0] - nss[i, ns - 1]) * inv_ds)
                for k in range(sptr[i], sptr[i + 1]):
                    c = scol[k]
                    vs[i, c] += ms[i, c] * a_s * sw[k]
            # N_zs on face i (the outer faces stay free)
            if 0 < i < nz:
                for j in range(ns):
                    d[j] = (vs[i, j] - vs[i - 1, j]) * inv_dz
                memory(psi_zs, i, b_f[i], a_f[i], d, ns)
                for j in range(ns - 1):
                    nzs[i, j] += g_h[i, j] * ((vz[i, j + 1] - vz[i, j]) * inv_ds + d[j])
                nzs[i, ns - 1] += g_h[i, ns - 1] * ((vz[i, 0] - vz[i, ns - 1]) * inv_ds + d[ns - 1])
            # N_zz, N_ss in cell i - 1
            if i > 0:
                r = i - 1
                for j in range(ns):
                    d[j] = (vz[r + 1, j] - vz[r, j]) * inv_dz
                memory(psi_n, r, b_c[r], a_c[r], d, ns)
                e[0] = (vs[r, 0] - vs[r, ns - 1]) * inv_ds
                for j in range(1, ns):
                    e[j] = (vs[r, j] - vs[r, j - 1]) * inv_ds
                for j in range(ns):
                    nzz[r, j] += a_h[r, j] * d[j] + b_h[r, j] * e[j]
                    nss[r, j] += b_h[r, j] * d[j] + a_h[r, j] * e[j]
        for k in range(rxz_index.shape[0]):
            out[n, rxz_owner[k]] += rxz_weight[k] * vzf[rxz_index[k]]
        for k in range(rxs_index.shape[0]):
            out[n, rxs_owner[k]] += rxs_weight[k] * vsf[rxs_index[k]]


_memory_compiled = jit(_memory) or _memory  # called from the compiled loop only
_run_compiled = jit(_run_loops)


@dataclass(frozen=True)
class Transducers:
    """Weights of the Tx traction and the receivers' sensing on both velocity grids; the axial and
    circumferential parts already carry the direction's components."""

    source_z: PatchWeights
    source_s: PatchWeights
    receiver_z: PatchWeights
    receiver_s: PatchWeights
    n_rx: int


def ring_transducers(medium: Medium, rings: RingLayout, direction: tuple[float, float]) -> Transducers:
    grid = medium.grid
    axial, circumferential = direction

    def scaled(w: PatchWeights, factor: float) -> PatchWeights:
        return PatchWeights(w.index, w.weight * factor, w.owner)

    return Transducers(
        scaled(tx_weights(grid, rings, on_faces=True), axial),
        scaled(tx_weights(grid, rings, s_offset=0.5), circumferential),
        scaled(rx_weights(grid, rings, on_faces=True), axial),
        scaled(rx_weights(grid, rings, s_offset=0.5), circumferential),
        len(rings.rx_angles),
    )


def point_receivers(coverages_z: list[np.ndarray], coverages_s: list[np.ndarray],
                    direction: tuple[float, float]) -> tuple[PatchWeights, PatchWeights]:
    """Receivers sensing ``direction`` (axial, circumferential) over the given coverages."""
    z, s = averaging_weights(coverages_z), averaging_weights(coverages_s)
    return (PatchWeights(z.index, z.weight * direction[0], z.owner),
            PatchWeights(s.index, s.weight * direction[1], s.owner))


def run(op: InplaneOperator, state: InplaneState, amplitude: np.ndarray, t: Transducers) -> np.ndarray:
    """Advance ``len(amplitude)`` steps; returns the receivers' output [n_steps, n_rx] (at half steps)."""
    dtype = state.vs.dtype
    amplitude = np.ascontiguousarray(amplitude, dtype=dtype)
    out = np.zeros((amplitude.size, t.n_rx), dtype=np.float64)
    nz, ns = state.vs.shape
    if _run_compiled is None:
        fz, fs = np.zeros(state.vz.size, dtype), np.zeros(state.vs.size, dtype)
        for n, amp in enumerate(amplitude):
            fz[t.source_z.index] = amp * t.source_z.weight
            fs[t.source_s.index] = amp * t.source_s.weight
            step_numpy(op, state, fz.reshape(state.vz.shape), fs.reshape(state.vs.shape))
            np.add.at(out[n], t.receiver_z.owner, t.receiver_z.weight * state.vz.ravel()[t.receiver_z.index])
            np.add.at(out[n], t.receiver_s.owner, t.receiver_s.weight * state.vs.ravel()[t.receiver_s.index])
        return out
    zptr, zcol, zw = t.source_z.by_row(nz + 1, ns)
    sptr, scol, sw = t.source_s.by_row(nz, ns)
    p = op.cpml
    _run_compiled(op.dt_over_mass_z, op.dt_over_mass_s, op.a_h, op.b_h, op.g_h, dtype.type(op.inv_dz),
                  dtype.type(op.inv_ds), p.a_cell, p.b_cell, p.a_face, p.b_face, state.vz, state.vs, state.nzz,
                  state.nss, state.nzs, state.psi_vz, state.psi_vs, state.psi_n, state.psi_zs, amplitude, amplitude,
                  zptr, zcol, zw.astype(dtype), sptr, scol, sw.astype(dtype),
                  t.receiver_z.index.astype(np.int64), t.receiver_z.weight.astype(np.float64),
                  t.receiver_z.owner.astype(np.int64), t.receiver_s.index.astype(np.int64),
                  t.receiver_s.weight.astype(np.float64), t.receiver_s.owner.astype(np.int64), out)
    state.step += amplitude.size
    return out


def energy_j(op: InplaneOperator, before: InplaneState, after: InplaneState, dz_m: float, ds_m: float) -> float:
    """The leapfrog's conserved energy between two consecutive states (J): kinetic at the half step,
    plus N^n . C^-1 N^(n+1) / 2 with the plane-stress compliance (1 / E h) [[1, -nu], [-nu, 1]] and
    N_zs^n N_zs^(n+1) / (2 mu h)."""
    if after.step != before.step + 1:
        raise ValueError("energy needs two consecutive states")
    dt = op.dt_s
    f64 = lambda a: a.astype(np.float64)  # noqa: E731
    kinetic = 0.5 * (np.sum(f64(after.vz) ** 2 * dt / op.dt_over_mass_z)
                     + np.sum(f64(after.vs) ** 2 * dt / op.dt_over_mass_s))
    a, b = f64(op.a_h) / dt, f64(op.b_h) / dt  # h A and h B
    det = a * a - b * b
    z0, s0, z1, s1 = f64(before.nzz), f64(before.nss), f64(after.nzz), f64(after.nss)
    normal = 0.5 * np.sum((a * (z0 * z1 + s0 * s1) - b * (z0 * s1 + s0 * z1)) / det)
    live = op.g_h > 0
    shear = 0.5 * np.sum(f64(before.nzs)[live] * f64(after.nzs)[live] * dt / f64(op.g_h)[live])
    return float((kinetic + normal + shear) * dz_m * ds_m)


def simulate(medium: Medium, dt_s: float, absorber: Cpml, rings: RingLayout, amplitude: np.ndarray,
             direction: tuple[float, float], dtype: type = np.float32) -> np.ndarray:
    """The Rx ring's outputs [n_steps, n_rx] (velocity along ``direction``) for a Tx traction
    amplitude[n] (Pa) along ``direction`` (axial, circumferential)."""
    grid = medium.grid
    op = inplane_operator(medium, dt_s, absorber, dtype)
    state = InplaneState.zeros(grid.nz, grid.ns, dtype)
    return run(op, state, amplitude, ring_transducers(medium, rings, direction))


__all__ = ["InplaneOperator", "InplaneState", "Transducers", "energy_j", "inplane_operator", "point_receivers",
           "ring_transducers", "run", "simulate", "step_numpy"]

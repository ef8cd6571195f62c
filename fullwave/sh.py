"""The scalar SH (torsional) model: time stepping of the wall's circumferential motion.

    (rho h + m_added) dv/dt = d/dz (tau_z) + d/ds (tau_s) + f,    v = dw/dt,
    d tau_z / dt = mu h dv/dz,    d tau_s / dt = mu h dv/ds,

w the circumferential displacement, tau the shear force per unit length (N/m), f the Tx
traction (Pa). Staggered grid: v at cell centres, tau_z on the faces between cells in z,
tau_s between cells in s (periodic). Leapfrog in time: v at half steps (n + 1/2) dt, the forces
at whole steps. Face stiffnesses are harmonic means of the two cells (springs in series: force
continuity across a thickness step); the grid's outer faces carry tau_z = 0 (free ends, or the
free outer edge of an absorbing layer). Stable for c dt sqrt(1/dz^2 + 1/ds^2) <= 1.

This treats w as a scalar (antiplane-like) field: exact for the axisymmetric T(0,1) wave and
its reflections, approximate for obliquely scattered waves (their polarisation stays
circumferential here; fullwave/inplane.py has the true in-plane elasticity).

Two implementations of one step: ``step_numpy`` (the reference, vectorised) and a fused numba
loop (``run``); tests hold them equal.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from fullwave.absorber import Cpml
from fullwave.compiled import jit, kernel_array
from fullwave.medium import Medium, harmonic_mean
from fullwave.transducers import PatchWeights, RingLayout, rx_weights, tx_weights


@dataclass(frozen=True)
class ShOperator:
    """Per-node update coefficients, all already multiplied by dt."""

    dt_over_mass: np.ndarray  # [nz, ns]  dt / (rho h + m)          (s m^2 / kg)
    kz: np.ndarray  # [nz + 1, ns]  dt mu h on z faces, 0 on the outer faces
    ks: np.ndarray  # [nz, ns]  dt mu h between s and s + 1
    inv_dz: float
    inv_ds: float
    cpml: Cpml
    dt_s: float


@dataclass
class ShState:
    """v [nz, ns] at step n - 1/2, tau_z [nz + 1, ns] and tau_s [nz, ns] at step n, and the CPML memory."""

    v: np.ndarray
    tau_z: np.ndarray
    tau_s: np.ndarray
    psi_v: np.ndarray  # memory of d tau_z / dz at cells
    psi_tau: np.ndarray  # memory of dv/dz at faces
    step: int = 0

    @classmethod
    def zeros(cls, nz: int, ns: int, dtype: type = np.float32) -> ShState:
        return cls(np.zeros((nz, ns), dtype), np.zeros((nz + 1, ns), dtype), np.zeros((nz, ns), dtype),
                   np.zeros((nz, ns), dtype), np.zeros((nz + 1, ns), dtype))

    def copy(self) -> ShState:
        return ShState(self.v.copy(), self.tau_z.copy(), self.tau_s.copy(), self.psi_v.copy(), self.psi_tau.copy(),
                       self.step)


def sh_operator(medium: Medium, dt_s: float, cpml: Cpml, dtype: type = np.float32) -> ShOperator:
    grid = medium.grid
    mu_h = medium.shear_stiffness_n_m
    kz = np.zeros((grid.nz + 1, grid.ns))
    kz[1:-1] = harmonic_mean(mu_h[:-1], mu_h[1:])
    ks = harmonic_mean(mu_h, np.roll(mu_h, -1, axis=1))
    return ShOperator(kernel_array(dt_s / medium.areal_mass_kg_m2, dtype), kernel_array(dt_s * kz, dtype),
                      kernel_array(dt_s * ks, dtype), 1.0 / grid.dz_m, 1.0 / grid.ds_m, cpml.astype(dtype), dt_s)


def step_numpy(op: ShOperator, state: ShState, force: np.ndarray) -> None:
    """One leapfrog step in place; ``force`` [nz, ns] is the traction at step n (Pa)."""
    v, tz, ts = state.v, state.tau_z, state.tau_s
    p = op.cpml
    dtz = (tz[1:] - tz[:-1]) * op.inv_dz
    state.psi_v[:] = p.b_cell[:, None] * state.psi_v + p.a_cell[:, None] * dtz
    dts = (ts - np.roll(ts, 1, axis=1)) * op.inv_ds
    v += op.dt_over_mass * (dtz + state.psi_v + dts + force)
    dvz = (v[1:] - v[:-1]) * op.inv_dz
    psi = state.psi_tau[1:-1]
    psi[:] = p.b_face[1:-1, None] * psi + p.a_face[1:-1, None] * dvz
    tz[1:-1] += op.kz[1:-1] * (dvz + psi)
    ts += op.ks * (np.roll(v, -1, axis=1) - v) * op.inv_ds
    state.step += 1


def _run_loops(dt_over_mass, kz, ks, inv_dz, inv_ds, a_c, b_c, a_f, b_f, v, tz, ts, psi_v, psi_t, amplitude,
               src_ptr, src_col, src_weight, rx_index, rx_weight, rx_owner, out):  # pragma: no cover - numba
    # One pass over the rows per step: row i's velocities, then the forces that need only rows <= i
    # (tau_z on the face before row i, tau_s of row i), so each row is touched while in cache.
    nz, ns = v.shape
    vf = v.reshape(nz * ns)
    row = np.empty(ns, dtype=v.dtype)
    for n in range(amplitude.shape[0]):
        amp = amplitude[n]
        for i in range(nz):
            bc, ac = b_c[i], a_c[i]
            if ac == 0.0 and bc == 0.0:  # outside the absorbing layers the memory stays zero
                for j in range(ns):
                    row[j] = (tz[i + 1, j] - tz[i, j]) * inv_dz
            else:
                for j in range(ns):
                    dtz = (tz[i + 1, j] - tz[i, j]) * inv_dz
                    psi = bc * psi_v[i, j] + ac * dtz
                    psi_v[i, j] = psi
                    row[j] = dtz + psi
            row[0] += (ts[i, 0] - ts[i, ns - 1]) * inv_ds
            for j in range(1, ns):
                row[j] += (ts[i, j] - ts[i, j - 1]) * inv_ds
            for j in range(ns):
                v[i, j] += dt_over_mass[i, j] * row[j]
            for k in range(src_ptr[i], src_ptr[i + 1]):
                c = src_col[k]
                v[i, c] += dt_over_mass[i, c] * amp * src_weight[k]
            if i > 0:
                bf, af = b_f[i], a_f[i]
                if af == 0.0 and bf == 0.0:
                    for j in range(ns):
                        tz[i, j] += kz[i, j] * (v[i, j] - v[i - 1, j]) * inv_dz
                else:
                    for j in range(ns):
                        dvz = (v[i, j] - v[i - 1, j]) * inv_dz
                        psi = bf * psi_t[i, j] + af * dvz
                        psi_t[i, j] = psi
                        tz[i, j] += kz[i, j] * (dvz + psi)
            for j in range(ns - 1):
                ts[i, j] += ks[i, j] * (v[i, j + 1] - v[i, j]) * inv_ds
            ts[i, ns - 1] += ks[i, ns - 1] * (v[i, 0] - v[i, ns - 1]) * inv_ds
        for k in range(rx_index.shape[0]):
            out[n, rx_owner[k]] += rx_weight[k] * vf[rx_index[k]]


_run_compiled = jit(_run_loops)


def run(op: ShOperator, state: ShState, amplitude: np.ndarray, source: PatchWeights, receivers: PatchWeights,
        n_rx: int) -> np.ndarray:
    """Advance ``len(amplitude)`` steps; the Tx traction at step n is amplitude[n] x source weights (Pa).

    Returns the receivers' averaged v [n_steps, n_rx] at times (step + 1/2) dt of each step.
    """
    dtype = state.v.dtype
    amplitude = np.ascontiguousarray(amplitude, dtype=dtype)
    out = np.zeros((amplitude.size, n_rx), dtype=np.float64)
    if _run_compiled is None:
        force = np.zeros(state.v.size, dtype=dtype)
        for n, amp in enumerate(amplitude):
            force[source.index] = amp * source.weight
            step_numpy(op, state, force.reshape(state.v.shape))
            np.add.at(out[n], receivers.owner, receivers.weight * state.v.ravel()[receivers.index])
        return out
    p = op.cpml
    ptr, col, weight = source.by_row(*state.v.shape)
    _run_compiled(op.dt_over_mass, op.kz, op.ks, dtype.type(op.inv_dz), dtype.type(op.inv_ds), p.a_cell, p.b_cell,
                  p.a_face, p.b_face, state.v, state.tau_z, state.tau_s, state.psi_v, state.psi_tau, amplitude,
                  ptr, col, weight.astype(dtype), receivers.index.astype(np.int64),
                  receivers.weight.astype(np.float64), receivers.owner.astype(np.int64), out)
    state.step += amplitude.size
    return out


def energy_j(op: ShOperator, before: ShState, after: ShState, dz_m: float, ds_m: float) -> float:
    """The leapfrog's conserved energy between two consecutive states (J): kinetic at the half step
    of ``after`` plus strain energy tau^n . tau^(n+1) / (2 mu h) (exactly constant without sources
    and absorbing layers; positive under the stability limit)."""
    if after.step != before.step + 1:
        raise ValueError("energy needs two consecutive states")
    dt = op.dt_s
    v = after.v.astype(np.float64)
    kinetic = 0.5 * np.sum(v * v * dt / op.dt_over_mass)
    strain = 0.0
    for k, a, b in ((op.kz, before.tau_z, after.tau_z), (op.ks, before.tau_s, after.tau_s)):
        live = k > 0
        strain += 0.5 * np.sum(a[live].astype(np.float64) * b[live] * dt / k[live])
    return float((kinetic + strain) * dz_m * ds_m)


def simulate(medium: Medium, dt_s: float, absorber: Cpml, rings: RingLayout, amplitude: np.ndarray,
             direction: tuple[float, float], dtype: type = np.float32) -> np.ndarray:
    """The Rx ring's outputs [n_steps, n_rx] for a Tx traction amplitude[n] (Pa) along ``direction``
    (axial, circumferential): only its circumferential part drives this model, and a receiver senses
    the circumferential velocity times the same component."""
    grid = medium.grid
    op = sh_operator(medium, dt_s, absorber, dtype)
    state = ShState.zeros(grid.nz, grid.ns, dtype)
    circumferential = direction[1]
    out = run(op, state, circumferential * np.asarray(amplitude), tx_weights(grid, rings), rx_weights(grid, rings),
              len(rings.rx_angles))
    return circumferential * out


__all__ = ["ShOperator", "ShState", "energy_j", "run", "sh_operator", "simulate", "step_numpy"]

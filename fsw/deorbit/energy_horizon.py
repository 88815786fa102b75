"""The de-orbit controller's energy-descent law over a horizon of a few pulses (`law = "energy"`).

Why a law on the energy. With 80-s pulses of the full 15 A·m² one pulse changes a rate by ~1·10⁻³ rad/s,
as much as a whole 1-rad swing of this spacecraft, so a plan that is linear about the target, with the
field frozen in body axes (the `"mpc"` law), is not a model of what a pulse does at tens of degrees; where
it is wrong it picks pulses that add energy, and under the IGRF degree-13 field the 45° start was pumped
over 180°. This law instead predicts each candidate with the *nonlinear* motion relative to the orbital
frame (gravity gradient, the sail's moment, Euler's equations: `relative_motion.relative_rhs`) and the kit's
moment p × B, the field in orbital axes from the forecast along the orbit (the onboard field model on the
target) turned into body axes along the predicted attitude, and scores it by what is conserved when the
magnets are screened: the Jacobi energy of the motion relative to the orbital frame (:func:`jacobi_energy`)

    E = ½ ω_relᵀ J ω_rel + (3/2) n² ĉᵀJĉ − ½ n² ŷᵀJŷ − k_a (s·v̂_x|v̂_x|/2 + (1 − s)·v̂_x)

(ĉ nadir, ŷ the orbit normal's −, v̂ the flight direction, all in body axes; s the sail's share of the area
the flow sees). Its minimum is the target (sail broadside to the flow, roll about the flow at a gravity-
gradient minimum), it is constant on the free motion, and the kit changes it by ∫ M·ω_rel dt: a pulse that
takes energy out is one that damps, roll included, whatever the angle.

The choice, once per period T: every first move (each channel closed, or open with polarity ±1 for one of
`widths_s`: 80 or 100 s, 25 pairs) followed by every continuation of `horizon − 1` periods of full-period
pulses or nothing per channel (9 per period) is propagated (RK4, `substeps` steps a period, the moment on
while the channel is open; 2,275 periods for a horizon of 3, ~0.1 s); a sequence costs its energy at the
end of the horizon plus `energy_price` × the joules of its openings and turns. A first move is worth the
least cost of its sequences. The closed first move is taken unless another one is worth less by more than
`margin` × the energy the pulse moves in or out (robustness to a relative error of the field model), and
nothing opens while the energy is below `deadband_J` over the target's. The controller's defaults
(`ControllerConfig`): no price, no margin, no dead band, and below the energy of a 0.8-rad yaw swing
(`energy_switch_rad`) the "mpc" choice decides instead: near the target its linear model holds, and there
an 80-s pulse is too coarse for a choice over three periods alone to take energy out (on the law's own
dynamics with the degree-13 field along the orbit, yaw stalled at 0.3–0.6 rad). The `pumps` guard applies
the same prediction to another law's first move. All inputs are arguments (time, state, forecast): no
clock, no hardware.
"""
from __future__ import annotations


import numpy as np
from numba import njit

from .relative_motion import rk4_step


@njit(cache=True)
def jacobi_energy(R, w, J, n, ka, sail_share):
    """E [J] of the motion relative to the orbital frame (see the module docstring); R = R_bo."""
    c, y, v = R[2, :], R[1, :], R[0, :]
    kin = 0.5 * (J[0] * w[0] ** 2 + J[1] * w[1] ** 2 + J[2] * w[2] ** 2)
    gg = 1.5 * n * n * (J[0] * c[0] ** 2 + J[1] * c[1] ** 2 + J[2] * c[2] ** 2)
    rot = -0.5 * n * n * (J[0] * y[0] ** 2 + J[1] * y[1] ** 2 + J[2] * y[2] ** 2)
    aero = -ka * (sail_share * 0.5 * v[0] * abs(v[0]) + (1.0 - sail_share) * v[0])
    return kin + gg + rot + aero


@njit(cache=True)
def propagate_period(R, w, J, n, ka, s, h, substeps, b_o, k0, move, dipole):
    """The motion over one period of `substeps` steps of h with `move` = (pol_pitch, steps_pitch, pol_yaw,
    steps_yaw): the pitch magnet (body z) at polarity pol_pitch for its first steps_pitch steps, the yaw
    magnet (body y) likewise; the field b_o[k0 + i] (orbital axes) over step i."""
    for i in range(substeps):
        m = np.zeros(3)
        if i < move[1]:
            m[2] += dipole * move[0]
        if i < move[3]:
            m[1] += dipole * move[2]
        R, w = rk4_step(R, w, J, n, ka, s, h, m, b_o[k0 + i])
    return R, w


@njit(cache=True)
def sequence_energies(R0, w0, J, n, ka, s, h, substeps, b_o, first, cont, horizon, dipole):
    """E at the end of the horizon of every sequence: first move `first[f]` then `horizon − 1` periods of
    `cont` moves; returns (F, K^(horizon−1)), the continuation index in base K, the first period's most
    significant."""
    F, K = first.shape[0], cont.shape[0]
    L = K ** (horizon - 1)
    out = np.empty((F, L))
    Rs = np.empty((F, 3, 3))
    ws = np.empty((F, 3))
    for f in range(F):
        Rs[f], ws[f] = propagate_period(R0.copy(), w0.copy(), J, n, ka, s, h, substeps, b_o, 0, first[f], dipole)
    level_R, level_w = Rs, ws
    for p in range(1, horizon):
        M = level_R.shape[0]
        nR = np.empty((M * K, 3, 3))
        nw = np.empty((M * K, 3))
        for i in range(M):
            for k in range(K):
                nR[i * K + k], nw[i * K + k] = propagate_period(level_R[i].copy(), level_w[i].copy(), J, n, ka, s,
                                                                h, substeps, b_o, p * substeps, cont[k], dipole)
        level_R, level_w = nR, nw
    for i in range(F * L):
        out[i // L, i % L] = jacobi_energy(level_R[i], level_w[i], J, n, ka, s)
    return out


def moves(widths_s, period_s: float, substeps: int) -> np.ndarray:
    """The first moves: (pol_pitch, steps_pitch, pol_yaw, steps_yaw) of each channel closed or open ±1 for
    each width (rounded to whole steps), all pairs, the closed pair first."""
    h = period_s / substeps
    one = [(0, 0)] + [(p, int(round(w / h))) for p in (1, -1) for w in widths_s]
    return np.array([(a[0], a[1], b[0], b[1]) for a in one for b in one], dtype=np.int64)


def continuation_moves(substeps: int) -> np.ndarray:
    """The later periods' moves: each channel closed or open ±1 for the whole period."""
    one = [(0, 0), (1, substeps), (-1, substeps)]
    return np.array([(a[0], a[1], b[0], b[1]) for a in one for b in one], dtype=np.int64)


def move_joules(move, acting, polarity, opening_J: float, turn_J: float) -> float:
    """The kit's energy for a move after (acting, polarity) per channel: an opening unless open at that
    polarity already, a turn when the magnet's polarity differs."""
    total = 0.0
    for ch, (pol, steps) in enumerate(((move[0], move[1]), (move[2], move[3]))):
        if pol == 0 or steps == 0:
            continue
        if acting[ch] == pol:
            continue
        total += opening_J + (turn_J if polarity[ch] != pol else 0.0)
    return total


def sequence_joules(first, cont, horizon, acting, polarity, opening_J, turn_J, substeps) -> np.ndarray:
    """(F, K^(horizon−1)) joules of each sequence (the same order as :func:`sequence_energies`)."""
    F, K = first.shape[0], cont.shape[0]
    out = np.zeros((F, K ** (horizon - 1)))
    for f in range(F):
        states = [(move_joules(first[f], acting, polarity, opening_J, turn_J),
                   _after(first[f], acting, polarity, substeps))]
        for _ in range(1, horizon):
            nxt = []
            for joules, (act, pol) in states:
                for k in range(K):
                    nxt.append((joules + move_joules(cont[k], act, pol, opening_J, turn_J),
                                _after(cont[k], act, pol, substeps)))
            states = nxt
        out[f] = [j for j, _ in states]
    return out


def _after(move, acting, polarity, substeps):
    """(acting, polarity) after a move: a channel open to the end of the period stays open (the next
    pulse of that polarity extends it), else closed; the polarity is the last one used."""
    act, pol = list(acting), list(polarity)
    for ch, (p, steps) in enumerate(((move[0], move[1]), (move[2], move[3]))):
        act[ch] = int(p) if p != 0 and steps >= substeps else 0
        if p != 0 and steps > 0:
            pol[ch] = int(p)
    return tuple(act), tuple(pol)


def choose(R_bo, w_rel, b_orbital_T, *, J, n, ka, sail_share, dipole_Am2, period_s, substeps, horizon,
           widths_s, acting, polarity, opening_J, turn_J, energy_price, margin, deadband_J):
    """The first move of least worth (module docstring) and the table behind it.

    b_orbital_T: the field in orbital axes at the middle of every step of the horizon (horizon·substeps, 3).
    Returns (move (4,), worth (F,), first (F, 4), E0): `move` the chosen (pol_pitch, steps_pitch, pol_yaw,
    steps_yaw)."""
    first = moves(widths_s, period_s, substeps)
    cont = continuation_moves(substeps)
    h = period_s / substeps
    Jv = np.asarray(J, float)
    R0, w0 = np.asarray(R_bo, float), np.asarray(w_rel, float)
    E0 = float(jacobi_energy(R0, w0, Jv, n, ka, sail_share))
    E = sequence_energies(R0, w0, Jv, n, ka, sail_share, h, substeps, np.asarray(b_orbital_T, float), first,
                          cont, horizon, dipole_Am2)
    cost = E + energy_price * sequence_joules(first, cont, horizon, acting, polarity, opening_J, turn_J, substeps)
    worth = cost.min(axis=1)
    k = int(np.argmin(worth))
    if k != 0:
        moved = abs(float(E[k, 0] - E[0, 0]))  # the energy the first move moves (then coasting)
        if worth[0] - worth[k] <= margin * moved or E0 - _e_min(Jv, n, ka, sail_share) < deadband_J:
            k = 0
    return first[k], worth, first, E0


def _e_min(J, n, ka, sail_share) -> float:
    """E at the target at rest (body axes on the orbital axes)."""
    return float(jacobi_energy(np.eye(3), np.zeros(3), np.asarray(J, float), n, ka, sail_share))


def deadband_energy_J(J, n, ka, swing_rad: float) -> float:
    """The energy above the target's of a yaw swing of `swing_rad` (LVLH stiffness n²(J_y − J_x) + k_a)."""
    return 0.5 * (n * n * (J[1] - J[0]) + ka) * swing_rad ** 2 if swing_rad > 0 else 0.0


def width_s(steps: int, period_s: float, substeps: int) -> float:
    return steps * period_s / substeps if steps else 0.0



def pumps(R_bo, w_rel, b_orbital_T, move, *, J, n, ka, sail_share, dipole_Am2, period_s, substeps, horizon,
          floor_J) -> bool:
    """Whether `move` (pol_pitch, steps_pitch, pol_yaw, steps_yaw), followed by its best continuation, ends the
    horizon with more energy than staying closed now and continuing at best, while the energy is above
    `floor_J` over the target's: the guard of another law's choice (``"mpc"`` with `nonlinear_guard_rad`)."""
    Jv = np.asarray(J, float)
    R0, w0 = np.asarray(R_bo, float), np.asarray(w_rel, float)
    if float(jacobi_energy(R0, w0, Jv, n, ka, sail_share)) - _e_min(Jv, n, ka, sail_share) <= floor_J:
        return False
    first = np.array([(0, 0, 0, 0), tuple(int(v) for v in move)], dtype=np.int64)
    E = sequence_energies(R0, w0, Jv, n, ka, sail_share, period_s / substeps, substeps,
                          np.asarray(b_orbital_T, float), first, continuation_moves(substeps), horizon, dipole_Am2)
    return bool(E[1].min() > E[0].min())

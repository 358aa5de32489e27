"""The strong peer: coopjax's two hard-switch steps and the carry metrics, written as a hand-tuned
CPU kernel in numba. It is what an engineer who knows the machine would write instead of coopjax.

    run = make_peer("filippov", "float64")   # or "rk4"; "float32"
    metrics = run(P, dt=1e-3, T=4.0)         # P from benchmarks.implementations.parameter_matrix

Both steps are coopjax's, operation for operation (coopjax/integration/filippov.py and
plain_rk4.py): the sliding-mode step with its located events (an impact, the force reaching F_lim,
the Kelvin-Voigt force passing 0, the end of a sliding mode) in up to three pieces a step, and plain
RK4 on the hard switch.
The metrics are coopjax's carry metrics over the force's path through each step (min_grip,
peak_grip, slip, crush, impact, rms_lag) with the same divergence rule. Unilateral contact,
alpha_b = 1, delta0 = 0; `benchmarks.__main__` checks the peer against coopjax before timing it.

Its shape is the one a C kernel of this step would have:
- struct of arrays, the batch innermost and contiguous: every state and parameter is a row of a
  block, and one loop over the block's samples does a whole (sub)step of one sample in registers;
- no data-dependent branch inside that loop (conditional expressions, which LLVM turns into
  selects), numpy's error model (no Python division check), no bounds checks;
- `prange` over blocks, the time loop inside the block: a block's state stays in L1 for the run;
- a piece of the step that no sample of the block needs is skipped for the block (coopjax skips
  it for the slab one device holds);
- float32 and float64 are separate compilations with typed constants, so float32 stays float32.

What LLVM makes of it, counted in its machine code (`vectorisation`; `python -m
benchmarks.strong_peer --vectorisation`; every `python -m benchmarks` run records it): on an
AVX-512 CPU both steps' loops over the block are vectorised, eight float64 samples per zmm
instruction (with the options of `vectorising_llvm`). Where numba's `math.sqrt` is a call to libm,
LLVM cannot vectorise the sliding-mode step's loop; `lanes=True` (`make_peer`) is the variant for
such a CPU. docs/speed.md gives the counts and the times.
"""

from __future__ import annotations

import functools
import math
import math as _math
import re

import numpy as np

from benchmarks.implementations import PER_ROBOT
from coopjax.integration.tableau import RK4

N_METRICS = 8  # min_grip, peak_grip, slip, crush, impact, rms_lag, finite, t_diverged
METRICS = ("min_grip", "peak_grip", "slip", "crush", "impact", "rms_lag")
# What coopjax computes when the peer is checked against it: the program the peer was transcribed
# from (plain RK4 chatters on F = F_lim, and another metric's fusion moves its round-off).
OURS = ("min_grip", "peak_grip", "slip", "crush", "impact", "min_swi", "rms_lag")
BLOCK = 64  # samples per block: 20 state rows x 64 x 8 B = 10 kB, in L1 with the block's parameters


def vectorising_llvm():
    """LLVM options without which the loop over a block stays scalar (process-wide, in this process).

    - `-inline-threshold`: numba compiles each helper apart and LLVM inlines only small ones; a call
      left in the loop stops its vectorisation (`-pass-remarks-missed=loop-vectorize` says "call
      instruction cannot be vectorized");
    - the runtime memory-check thresholds: the loop reads and writes some twenty rows of the block,
      and LLVM gives up at 8 (or 128) pointer comparisons ("too many memory checks needed").
    """
    import llvmlite.binding as llvm

    for option in (
        "-inline-threshold=100000",
        "-runtime-memory-check-threshold=100000",
        "-vectorize-memory-check-threshold=100000",
    ):
        llvm.set_option("", option)


@functools.lru_cache(maxsize=None)
def make_peer(step: str = "filippov", dtype: str = "float64", lanes: bool = False):
    """The compiled peer for a step ("filippov" or "rk4") and a dtype; compiles on first call.

    `lanes=True` takes square roots as `x ** 0.5`, which LLVM turns into its own square root
    instruction, where numba may call libm's `sqrt` for `math.sqrt`: a call LLVM cannot vectorise,
    which alone keeps the sliding-mode step's loop over the block scalar. On a CPU where numba's
    `math.sqrt` is vectorised anyway (this project's AVX-512 machine), both give the same machine
    code by `vectorisation`'s count, and the default is the plain one. Both give the same numbers:
    the power is the exact square root."""
    import numba

    T = np.dtype(dtype).type
    Z0, ONE, TWO, HALF = T(0.0), T(1.0), T(2.0), T(0.5)
    TWO_PI = T(2.0 * math.pi)
    INV_TWO_PI = T(1.0) / TWO_PI
    INF = T(np.inf)
    EPS = T(1e-9)  # as coopjax.integration.filippov.EPS
    SHORTEST = T(1e-2)  # as filippov.SHORTEST_EVENT
    PIECES = 3  # as filippov.PIECES
    C2, C12, C30, C56, C90 = T(2.0), T(12.0), T(30.0), T(56.0), T(90.0)
    C6, C20, C42, C72, C110 = T(6.0), T(20.0), T(42.0), T(72.0), T(110.0)
    # RK4 as coopjax's tableau has it: stage nodes, weights, and the dense output's polynomials,
    # whose second and third stages share one (`Tableau.dense_groups`).
    A2, A3, A4 = (T(a) for a in RK4.a[1:])
    W1, W2, W3, W4 = (T(w) for w in RK4.b)
    DEN = T(RK4.denominator)
    groups = RK4.dense_groups()
    assert [members for _, members in groups] == [(0,), (1, 2), (3,)], "the peer writes RK4's dense groups out"
    D1, D23, D4 = (tuple(T(c) for c in row) for row, _ in groups)
    base = 2 * len(PER_ROBOT)
    vectorising_llvm()
    jit = functools.partial(numba.njit, error_model="numpy", fastmath=False, boundscheck=False)
    inline = jit  # LLVM inlines them (see `vectorising_llvm`); numba's IR inlining compiled for minutes
    (iMv, iMr, iKg, iRg, iMc, iRc, iKc, iMf, iRf, iKf, imu, ibeta, iFlim, iKini, iKGP, iKGI, itau, itaue, iGe, irho) = (
        2 * j for j in range(len(PER_ROBOT))
    )

    @inline
    def small(x):
        """cos x, sin x by their Taylor series (Clock.advance)."""
        x2 = x * x
        c = ONE - x2 / C2 * (ONE - x2 / C12 * (ONE - x2 / C30 * (ONE - x2 / C56 * (ONE - x2 / C90))))
        s = x * (ONE - x2 / C6 * (ONE - x2 / C20 * (ONE - x2 / C42 * (ONE - x2 / C72 * (ONE - x2 / C110)))))
        return c, s

    @inline
    def advance(t, cos, sin, u):
        c, s = small(TWO_PI * u)
        return t + u, cos * c - sin * s, sin * c + cos * s

    @inline
    def bump(t, cos, sin, t0):
        """The unit rest-to-rest bump starting at whole second t0 (scenarios.bump)."""
        u = t - t0
        inside = (u >= Z0) and (u < ONE)
        v = (ONE - cos) if inside else Z0
        a = (TWO_PI * sin) if inside else Z0
        x = Z0 if u < Z0 else ((u - sin * INV_TWO_PI) if inside else ONE)
        return v, a, x

    @inline
    def command(P, b, t, cos, sin, s):
        """(v_cmd, a_cmd, x_ref) of the robot with sign s (scenarios/carry.py)."""
        gv, ga, gx = bump(t, cos, sin, Z0)
        cv, ca, cx = bump(t, cos, sin, ONE)
        rv, ra, rx = bump(t, cos, sin, TWO)
        sA = s * P[base + 1, b]
        A_c = P[base + 2, b]
        return (
            sA * gv + A_c * cv - TWO * sA * rv,
            sA * ga + A_c * ca - TWO * sA * ra,
            sA * gx + A_c * cx - TWO * sA * rx,
        )

    @inline
    def rates(P, i, b, s, x_r, v_r, v_v, q_c, x_f, v_f, Z, Y_e, F, on, F_c, cmd):
        """Robot i's nine rates under the switch-off field (on = False, force F) or the switch-on field
        (on = True, gamma and dZ/dt from the clamped force F_c): model.robot_field, alpha_b = 1."""
        v_cmd, a_cmd, x_ref = cmd
        F_lim = P[iFlim + i, b]
        if on:
            gamma = ONE - (P[iKini + i, b] + P[iKGP + i, b] * (F_c - F_lim) + P[iKGI + i, b] * Z)
            dZ = (F_c - F_lim) - P[itau + i, b] * Z
            dY = -P[itaue + i, b] * Y_e - P[irho + i, b] * Y_e
            v_ref = v_cmd
            a_ref = a_cmd
        else:
            gamma = ONE
            dZ = -P[itau + i, b] * Z - P[irho + i, b] * Z
            dY = (x_ref - x_r) - P[itaue + i, b] * Y_e
            v_ref = v_cmd + P[iGe + i, b] * Y_e
            a_ref = a_cmd + P[iGe + i, b] * dY
        M_c, M_r, M_f, mu = P[iMc + i, b], P[iMr + i, b], P[iMf + i, b], P[imu + i, b]
        g = (ONE - gamma) * P[ibeta + i, b]
        err = v_ref - v_r - g * v_f
        D = M_c * a_ref + P[iRc + i, b] * err + P[iKc + i, b] * q_c
        h = P[iRf + i, b] * v_f + P[iKf + i, b] * x_f
        f_ext = -s * F
        e_c = (D - M_c * f_ext / M_r + M_c * g * h / M_f) / (ONE + M_c * mu / M_r + M_c * g / M_f)
        return v_r, (mu * e_c + f_ext) / M_r, v_v, -mu * e_c / P[iMv + i, b], err, v_f, (e_c - h) / M_f, dZ, dY

    @inline
    def geometry(P, i, b, s, x_r, v_r, x_o, v_o):
        delta = s * (x_r - x_o)
        delta_dot = s * (v_r - v_o)
        return delta, delta_dot, P[iKg + i, b] * delta + P[iRg + i, b] * delta_dot

    @inline
    def force(kelvin, touching):
        return max(kelvin, Z0) if touching else Z0

    @inline
    def axpy(y, c, k):
        """y + c k for 20-tuples, written out: LLVM vectorises only innermost loops, so the loop over
        the block must contain no loop of its own."""
        return (
            y[0] + c * k[0],
            y[1] + c * k[1],
            y[2] + c * k[2],
            y[3] + c * k[3],
            y[4] + c * k[4],
            y[5] + c * k[5],
            y[6] + c * k[6],
            y[7] + c * k[7],
            y[8] + c * k[8],
            y[9] + c * k[9],
            y[10] + c * k[10],
            y[11] + c * k[11],
            y[12] + c * k[12],
            y[13] + c * k[13],
            y[14] + c * k[14],
            y[15] + c * k[15],
            y[16] + c * k[16],
            y[17] + c * k[17],
            y[18] + c * k[18],
            y[19] + c * k[19],
        )

    @inline
    def weighted(k1, k2, k3, k4):
        """W1 k1 + W2 k2 + W3 k3 + W4 k4 for 20-tuples (RK4's weights, to be divided by DEN)."""
        return (
            W1 * k1[0] + W2 * k2[0] + W3 * k3[0] + W4 * k4[0],
            W1 * k1[1] + W2 * k2[1] + W3 * k3[1] + W4 * k4[1],
            W1 * k1[2] + W2 * k2[2] + W3 * k3[2] + W4 * k4[2],
            W1 * k1[3] + W2 * k2[3] + W3 * k3[3] + W4 * k4[3],
            W1 * k1[4] + W2 * k2[4] + W3 * k3[4] + W4 * k4[4],
            W1 * k1[5] + W2 * k2[5] + W3 * k3[5] + W4 * k4[5],
            W1 * k1[6] + W2 * k2[6] + W3 * k3[6] + W4 * k4[6],
            W1 * k1[7] + W2 * k2[7] + W3 * k3[7] + W4 * k4[7],
            W1 * k1[8] + W2 * k2[8] + W3 * k3[8] + W4 * k4[8],
            W1 * k1[9] + W2 * k2[9] + W3 * k3[9] + W4 * k4[9],
            W1 * k1[10] + W2 * k2[10] + W3 * k3[10] + W4 * k4[10],
            W1 * k1[11] + W2 * k2[11] + W3 * k3[11] + W4 * k4[11],
            W1 * k1[12] + W2 * k2[12] + W3 * k3[12] + W4 * k4[12],
            W1 * k1[13] + W2 * k2[13] + W3 * k3[13] + W4 * k4[13],
            W1 * k1[14] + W2 * k2[14] + W3 * k3[14] + W4 * k4[14],
            W1 * k1[15] + W2 * k2[15] + W3 * k3[15] + W4 * k4[15],
            W1 * k1[16] + W2 * k2[16] + W3 * k3[16] + W4 * k4[16],
            W1 * k1[17] + W2 * k2[17] + W3 * k3[17] + W4 * k4[17],
            W1 * k1[18] + W2 * k2[18] + W3 * k3[18] + W4 * k4[18],
            W1 * k1[19] + W2 * k2[19] + W3 * k3[19] + W4 * k4[19],
        )

    @inline
    def weighted_dense(k1, k2, k3, k4, b1, b23, b4):
        """RK4's continuous extension's weights for 20-tuples, written out (see axpy)."""
        return (
            b1 * k1[0] + b23 * (k2[0] + k3[0]) + b4 * k4[0],
            b1 * k1[1] + b23 * (k2[1] + k3[1]) + b4 * k4[1],
            b1 * k1[2] + b23 * (k2[2] + k3[2]) + b4 * k4[2],
            b1 * k1[3] + b23 * (k2[3] + k3[3]) + b4 * k4[3],
            b1 * k1[4] + b23 * (k2[4] + k3[4]) + b4 * k4[4],
            b1 * k1[5] + b23 * (k2[5] + k3[5]) + b4 * k4[5],
            b1 * k1[6] + b23 * (k2[6] + k3[6]) + b4 * k4[6],
            b1 * k1[7] + b23 * (k2[7] + k3[7]) + b4 * k4[7],
            b1 * k1[8] + b23 * (k2[8] + k3[8]) + b4 * k4[8],
            b1 * k1[9] + b23 * (k2[9] + k3[9]) + b4 * k4[9],
            b1 * k1[10] + b23 * (k2[10] + k3[10]) + b4 * k4[10],
            b1 * k1[11] + b23 * (k2[11] + k3[11]) + b4 * k4[11],
            b1 * k1[12] + b23 * (k2[12] + k3[12]) + b4 * k4[12],
            b1 * k1[13] + b23 * (k2[13] + k3[13]) + b4 * k4[13],
            b1 * k1[14] + b23 * (k2[14] + k3[14]) + b4 * k4[14],
            b1 * k1[15] + b23 * (k2[15] + k3[15]) + b4 * k4[15],
            b1 * k1[16] + b23 * (k2[16] + k3[16]) + b4 * k4[16],
            b1 * k1[17] + b23 * (k2[17] + k3[17]) + b4 * k4[17],
            b1 * k1[18] + b23 * (k2[18] + k3[18]) + b4 * k4[18],
            b1 * k1[19] + b23 * (k2[19] + k3[19]) + b4 * k4[19],
        )

    @inline
    def load(y, b):
        return (
            y[0, b],
            y[1, b],
            y[2, b],
            y[3, b],
            y[4, b],
            y[5, b],
            y[6, b],
            y[7, b],
            y[8, b],
            y[9, b],
            y[10, b],
            y[11, b],
            y[12, b],
            y[13, b],
            y[14, b],
            y[15, b],
            y[16, b],
            y[17, b],
            y[18, b],
            y[19, b],
        )

    @inline
    def store(y, b, v):
        y[0, b] = v[0]
        y[1, b] = v[1]
        y[2, b] = v[2]
        y[3, b] = v[3]
        y[4, b] = v[4]
        y[5, b] = v[5]
        y[6, b] = v[6]
        y[7, b] = v[7]
        y[8, b] = v[8]
        y[9, b] = v[9]
        y[10, b] = v[10]
        y[11, b] = v[11]
        y[12, b] = v[12]
        y[13, b] = v[13]
        y[14, b] = v[14]
        y[15, b] = v[15]
        y[16, b] = v[16]
        y[17, b] = v[17]
        y[18, b] = v[18]
        y[19, b] = v[19]

    # --- the sliding-mode step -------------------------------------------------------------------

    @inline
    def robot_fields(P, i, b, s, st, x_o, v_o, a_o, F, in_c, kelvin, delta_dot, cmd):
        """Both fields of robot i and the switching data (filippov.fields)."""
        x_r, v_r, x_v, v_v, q_c, x_f, v_f, Z, Y_e = st
        F_lim = P[iFlim + i, b]
        r0 = rates(P, i, b, s, x_r, v_r, v_v, q_c, x_f, v_f, Z, Y_e, F, False, F, cmd)
        r1 = rates(P, i, b, s, x_r, v_r, v_v, q_c, x_f, v_f, Z, Y_e, F, True, max(F, F_lim), cmd)
        sd0 = P[iKg + i, b] * delta_dot + P[iRg + i, b] * s * (r0[1] - a_o)
        sd1 = P[iKg + i, b] * delta_dot + P[iRg + i, b] * s * (r1[1] - a_o)
        sigma = (kelvin if in_c else Z0) - F_lim
        return r0, r1, sd0, sd1, sigma

    @inline
    def raw_of(sd0, sd1):
        """filippov.sliding_weight: lambda* before its clip."""
        d = sd0 - sd1
        return sd0 / d if d > EPS else (ONE if sd0 >= Z0 else Z0)

    @inline
    def lam_of(sd0, sd1, sigma_n, theta_b, theta_a, hold, in_c, free, leave):
        """filippov.weight with the substep start's fractions."""
        raw = raw_of(sd0, sd1)
        lam_star = raw if free else min(max(raw, Z0), ONE)
        lam_star = T(leave) if leave >= 0 else lam_star
        lam = (ONE - theta_b) * lam_star if sigma_n < Z0 else theta_a + (ONE - theta_a) * lam_star
        lam = T(hold) if hold >= 0 else lam
        return lam if in_c else Z0

    @inline
    def blend(r0, r1, lam):
        return (
            r0[0],
            r0[1] + lam * (r1[1] - r0[1]),
            r0[2],
            r0[3] + lam * (r1[3] - r0[3]),
            r0[4] + lam * (r1[4] - r0[4]),
            r0[5],
            r0[6] + lam * (r1[6] - r0[6]),
            r0[7] + lam * (r1[7] - r0[7]),
            r0[8] + lam * (r1[8] - r0[8]),
        )

    @inline
    def fractions(sd0, sd1, sigma_n, h):
        below = sd0 * h > Z0
        theta_b = min(max(-sigma_n / (sd0 * h), Z0), ONE) if below else ONE
        above = -sd1 * h > Z0
        theta_a = min(max(sigma_n / (-sd1 * h), Z0), ONE) if above else ONE
        return theta_b, theta_a

    @inline
    def switching_time(in_c, sigma, sd0, sd1, F_lim, shortest):
        below = in_c and (sigma < Z0) and (sd0 > Z0)
        above = in_c and (sigma > Z0) and (sd1 < Z0)
        rate = sd0 if below else (-sd1 if above else ONE)
        tau = abs(sigma) / rate if (below or above) else INF
        tau = tau if tau > shortest else INF
        kelvin = sigma + F_lim
        crossing = in_c and (F_lim > Z0) and (sigma < Z0) and (kelvin * sd0 < Z0)
        tau0 = abs(kelvin) / abs(sd0) if crossing else INF
        tau0 = tau0 if tau0 > shortest else INF
        first = min(tau, tau0)
        hold = (1 if above else 0) if tau <= tau0 else -1
        return first, (hold if first < INF else -1)

    if lanes:

        @inline
        def root(x):
            """sqrt of x >= 0 as a power, which LLVM vectorises (see `make_peer`)."""
            return x**HALF

    else:

        @inline
        def root(x):
            return math.sqrt(x)

    @inline
    def impact_time(delta, delta_dot, s, a_r_off, a_o):
        delta_ddot = s * (a_r_off - a_o)
        disc = delta_dot * delta_dot - TWO * delta_ddot * delta
        real = (delta <= Z0) and (disc > Z0)
        den = delta_dot + root(disc if real else ONE)
        hits = real and (den > Z0)
        return -TWO * delta / den if hits else INF

    @inline
    def crossing(sn, rate, se, h):
        """filippov.crossing: where sigma, held through a piece of length h, reaches 0 in it."""
        hs = h if h > Z0 else ONE
        curvature = (se - sn - rate * hs) / (hs * hs)
        disc = rate * rate - T(4.0) * curvature * sn
        real = (sn <= Z0) and (se > Z0) and (disc >= Z0)
        r = root(disc if real else ONE)
        num = -TWO * sn if rate > Z0 else r - rate
        den = rate + r if rate > Z0 else TWO * curvature
        ok = real and (den > Z0)
        return min(max(num / den, Z0), h) if ok else h

    @inline
    def found(off, on_, sn, sd0, sd1, in_c, rate, kelvin_end, F_lim, h, fresh):
        """filippov.trial_crossing: (found, time, hold) on a piece's own solution."""
        se = kelvin_end - F_lim
        up = off and se > Z0
        down = on_ and se < Z0
        kelvin = sn + F_lim
        kink = in_c and (F_lim > Z0) and (kelvin * kelvin_end < Z0)
        tau = crossing(sn, sd0, se, h) if up else (crossing(-sn, -sd1, -se, h) if down else INF)
        sign = -ONE if kelvin > Z0 else ONE
        tau0 = crossing(sign * kelvin, sign * rate, sign * kelvin_end, h) if kink else INF
        hold = -1 if tau0 < tau else (0 if off else 1)
        return fresh and (up or down or kink), min(tau, tau0), hold

    @inline
    def sliding_exit(free, start, end, h):
        """filippov.sliding_exit: (found, time, hold) where lambda* left [0, 1] on a piece slid through."""
        down = free and end < Z0
        up = free and end > ONE
        # One return of selects: a tuple returned from branches is a phi of an LLVM struct, which
        # stops the loop over the block from vectorising ("instruction return type cannot be vectorized").
        den = (start - end) if down else ((end - start) if up else ONE)
        share = (start if down else ONE - start) / den
        return down or up, (min(max(share, Z0), ONE) * h) if (down or up) else INF, 1 if up else 0

    @inline
    def evaluate(P, b, y, t, cos, sin, on_L, on_R, off_L, off_R):
        """Both robots' fields at state y (a 20-tuple, coopjax's row order) and the body's a_o."""
        x_o, v_o = y[18], y[19]
        stL = (y[0], y[2], y[4], y[6], y[8], y[10], y[12], y[14], y[16])
        stR = (y[1], y[3], y[5], y[7], y[9], y[11], y[13], y[15], y[17])
        dL, ddL, kL = geometry(P, 0, b, ONE, stL[0], stL[1], x_o, v_o)
        dR, ddR, kR = geometry(P, 1, b, -ONE, stR[0], stR[1], x_o, v_o)
        inL = on_L or ((not off_L) and dL > Z0)
        inR = on_R or ((not off_R) and dR > Z0)
        FL, FR = force(kL, inL), force(kR, inR)
        a_o = (FL - FR) / P[base, b]
        fL = robot_fields(P, 0, b, ONE, stL, x_o, v_o, a_o, FL, inL, kL, ddL, command(P, b, t, cos, sin, ONE))
        fR = robot_fields(P, 1, b, -ONE, stR, x_o, v_o, a_o, FR, inR, kR, ddR, command(P, b, t, cos, sin, -ONE))
        return fL, fR, inL, inR, FL, FR, a_o, dL, ddL, dR, ddR

    @inline
    def assemble(rL, rR, v_o, a_o):
        return (
            rL[0],
            rR[0],
            rL[1],
            rR[1],
            rL[2],
            rR[2],
            rL[3],
            rR[3],
            rL[4],
            rR[4],
            rL[5],
            rR[5],
            rL[6],
            rR[6],
            rL[7],
            rR[7],
            rL[8],
            rR[8],
            v_o,
            a_o,
        )

    @inline
    def sigma_n_of(P, b, y, on_L, on_R):
        dL, _, kL = geometry(P, 0, b, ONE, y[0], y[2], y[18], y[19])
        dR, _, kR = geometry(P, 1, b, -ONE, y[1], y[3], y[18], y[19])
        return ((kL if (on_L or dL > Z0) else Z0) - P[iFlim, b], (kR if (on_R or dR > Z0) else Z0) - P[iFlim + 1, b])

    @inline
    def stage(
        P,
        b,
        y,
        k,
        c,
        t,
        cos,
        sin,
        on_L,
        on_R,
        impL,
        impR,
        sn_L,
        sn_R,
        tbL,
        taL,
        tbR,
        taR,
        holdL,
        holdR,
        frL,
        frR,
        lvL,
        lvR,
    ):
        """One of the stages after the first: the rates at y + c k, t + c, with the substep's plan,
        and each robot's unclipped lambda* there."""
        ys = axpy(y, c, k)
        ts, cs, ss = advance(t, cos, sin, c)
        gL, gR, jL, jR, _, _, a_s, _, _, _, _ = evaluate(P, b, ys, ts, cs, ss, on_L, on_R, impL, impR)
        lL = lam_of(gL[2], gL[3], sn_L, tbL, taL, holdL, jL, frL, lvL)
        lR = lam_of(gR[2], gR[3], sn_R, tbR, taR, holdR, jR, frR, lvR)
        return (
            assemble(blend(gL[0], gL[1], lL), blend(gR[0], gR[1], lR), ys[19], a_s),
            raw_of(gL[2], gL[3]),
            raw_of(gR[2], gR[3]),
        )

    @inline
    def substep(P, b, y, t, cos, sin, remaining, on_L, on_R, keptL, keptR, dt, last):
        """filippov.substep for one sample: the new state, the plan and the start's force."""
        sn_L, sn_R = sigma_n_of(P, b, y, on_L, on_R)
        fL, fR, inL, inR, FL, FR, a_o, dL, ddL, dR, ddR = evaluate(P, b, y, t, cos, sin, on_L, on_R, False, False)
        # The plan (filippov.plan), from the start's fields.
        shortest = SHORTEST * dt
        tauL, holdL = switching_time(inL, fL[4], fL[2], fL[3], P[iFlim, b], shortest)
        tauR, holdR = switching_time(inR, fR[4], fR[2], fR[3], P[iFlim + 1, b], shortest)
        hitL = INF if on_L else impact_time(dL, ddL, ONE, fL[0][1], a_o)
        hitR = INF if on_R else impact_time(dR, ddR, -ONE, fR[0][1], a_o)
        timeL, timeR = min(tauL, hitL), min(tauR, hitR)
        holdL = -1 if hitL < tauL else holdL
        holdR = -1 if hitR < tauR else holdR
        h = remaining if last else min(min(timeL, timeR), remaining)
        firstL = (timeL <= h) and (timeL <= remaining) and not last
        firstR = (timeR <= h) and (timeR <= remaining) and not last
        impL, impR = firstL and hitL <= tauL, firstR and hitR <= tauR
        holdL = keptL if keptL >= 0 else (holdL if firstL else -1)
        holdR = keptR if keptR >= 0 else (holdR if firstR else -1)
        tbL, taL = fractions(fL[2], fL[3], sn_L, h)
        tbR, taR = fractions(fR[2], fR[3], sn_R, h)
        # A robot sliding at the start slides through the piece, lambda* unclipped (filippov.substep).
        rawL, rawR = raw_of(fL[2], fL[3]), raw_of(fR[2], fR[3])
        frL = (
            inL and holdL < 0 and rawL > Z0 and rawL < ONE and not last and ((tbL < ONE) if sn_L < Z0 else (taL < ONE))
        )
        frR = (
            inR and holdR < 0 and rawR > Z0 and rawR < ONE and not last and ((tbR < ONE) if sn_R < Z0 else (taR < ONE))
        )
        # Leaving the surface at the start (filippov.substep): lambda* held at 1 (upwards) or 0.
        nearL = inL and holdL < 0 and ((tbL < ONE) if sn_L < Z0 else (taL < ONE))
        nearR = inR and holdR < 0 and ((tbR < ONE) if sn_R < Z0 else (taR < ONE))
        lvL = (1 if rawL >= ONE else (0 if rawL <= Z0 else -1)) if nearL else -1
        lvR = (1 if rawR >= ONE else (0 if rawR <= Z0 else -1)) if nearR else -1
        # Stage 0 (at the start), then the three others.
        lamL = lam_of(fL[2], fL[3], sn_L, tbL, taL, holdL, inL, frL, lvL)
        lamR = lam_of(fR[2], fR[3], sn_R, tbR, taR, holdR, inR, frR, lvR)
        k = assemble(blend(fL[0], fL[1], lamL), blend(fR[0], fR[1], lamR), y[19], a_o)
        k2, _, _ = stage(
            P,
            b,
            y,
            k,
            A2 * h,
            t,
            cos,
            sin,
            on_L,
            on_R,
            impL,
            impR,
            sn_L,
            sn_R,
            tbL,
            taL,
            tbR,
            taR,
            holdL,
            holdR,
            frL,
            frR,
            lvL,
            lvR,
        )
        k3, _, _ = stage(
            P,
            b,
            y,
            k2,
            A3 * h,
            t,
            cos,
            sin,
            on_L,
            on_R,
            impL,
            impR,
            sn_L,
            sn_R,
            tbL,
            taL,
            tbR,
            taR,
            holdL,
            holdR,
            frL,
            frR,
            lvL,
            lvR,
        )
        k4, endL, endR = stage(
            P,
            b,
            y,
            k3,
            A4 * h,
            t,
            cos,
            sin,
            on_L,
            on_R,
            impL,
            impR,
            sn_L,
            sn_R,
            tbL,
            taL,
            tbR,
            taR,
            holdL,
            holdR,
            frL,
            frR,
            lvL,
            lvR,
        )
        total = weighted(k, k2, k3, k4)
        # The switch held through the whole piece, below (off) or above (on) the surface.
        # Its sign by round-off does not decide: a robot on the surface holds what it leaves with.
        offL = inL and (holdL == 0 or (holdL < 0 and sn_L < Z0 and tbL >= ONE) or lvL == 0)
        onL_ = inL and (holdL == 1 or (holdL < 0 and sn_L > Z0 and taL >= ONE) or lvL == 1)
        offR = inR and (holdR == 0 or (holdR < 0 and sn_R < Z0 and tbR >= ONE) or lvR == 0)
        onR_ = inR and (holdR == 1 or (holdR < 0 and sn_R > Z0 and taR >= ONE) or lvR == 1)
        shL = max(sn_L, Z0) if onL_ else (min(sn_L, Z0) if offL else sn_L)
        shR = max(sn_R, Z0) if onR_ else (min(sn_R, Z0) if offR else sn_R)
        heldL = (offL, onL_, shL, fL[2], fL[3], inL, fL[2] + lamL * (fL[3] - fL[2]))
        heldR = (offR, onR_, shR, fR[2], fR[3], inR, fR[2] + lamR * (fR[3] - fR[2]))
        slides = (frL, rawL, endL, frR, rawR, endR)
        # The piece ends on the surface where its plan ended it at a switch (not a hold kept from an exit).
        return (
            total,
            h,
            impL,
            impR,
            holdL >= 0 and keptL < 0,
            holdR >= 0 and keptR < 0,
            FL,
            FR,
            heldL,
            heldR,
            k,
            k2,
            k3,
            k4,
            slides,
        )

    @inline
    def forces_at(P, b, y, on_L, on_R, off_L, off_R):
        dL, _, kL = geometry(P, 0, b, ONE, y[0], y[2], y[18], y[19])
        dR, _, kR = geometry(P, 1, b, -ONE, y[1], y[3], y[18], y[19])
        return force(kL, on_L or ((not off_L) and dL > Z0)), force(kR, on_R or ((not off_R) and dR > Z0))

    # --- plain RK4 on the hard switch --------------------------------------------------------------

    @inline
    def rates_w(P, i, b, s, x_r, v_r, v_v, q_c, x_f, v_f, Z, Y_e, F, w, cmd):
        """Robot i's nine rates for a switch value w (model.robot_field, alpha_b = 1)."""
        v_cmd, a_cmd, x_ref = cmd
        F_lim = P[iFlim + i, b]
        off = ONE - w
        gamma = ONE - w * (P[iKini + i, b] + P[iKGP + i, b] * (F - F_lim) + P[iKGI + i, b] * Z)
        dZ = w * (F - F_lim) - P[itau + i, b] * Z - off * (P[irho + i, b] * Z)
        dY = off * (x_ref - x_r) - P[itaue + i, b] * Y_e - w * (P[irho + i, b] * Y_e)
        v_ref = v_cmd + off * (P[iGe + i, b] * Y_e)
        a_ref = a_cmd + off * (P[iGe + i, b] * dY)
        M_c, M_r, M_f, mu = P[iMc + i, b], P[iMr + i, b], P[iMf + i, b], P[imu + i, b]
        g = (ONE - gamma) * P[ibeta + i, b]
        err = v_ref - v_r - g * v_f
        D = M_c * a_ref + P[iRc + i, b] * err + P[iKc + i, b] * q_c
        h = P[iRf + i, b] * v_f + P[iKf + i, b] * x_f
        f_ext = -s * F
        e_c = (D - M_c * f_ext / M_r + M_c * g * h / M_f) / (ONE + M_c * mu / M_r + M_c * g / M_f)
        return v_r, (mu * e_c + f_ext) / M_r, v_v, -mu * e_c / P[iMv + i, b], err, v_f, (e_c - h) / M_f, dZ, dY

    @inline
    def hard_field(P, b, y, t, cos, sin):
        x_o, v_o = y[18], y[19]
        dL, _, kL = geometry(P, 0, b, ONE, y[0], y[2], x_o, v_o)
        dR, _, kR = geometry(P, 1, b, -ONE, y[1], y[3], x_o, v_o)
        FL, FR = force(kL, dL > Z0), force(kR, dR > Z0)
        cL, cR = command(P, b, t, cos, sin, ONE), command(P, b, t, cos, sin, -ONE)
        wL = ONE if FL >= P[iFlim, b] else Z0
        wR = ONE if FR >= P[iFlim + 1, b] else Z0
        rL = rates_w(P, 0, b, ONE, y[0], y[2], y[6], y[8], y[10], y[12], y[14], y[16], FL, wL, cL)
        rR = rates_w(P, 1, b, -ONE, y[1], y[3], y[7], y[9], y[11], y[13], y[15], y[17], FR, wR, cR)
        return assemble(rL, rR, v_o, (FL - FR) / P[base, b])

    # --- the loop, the metrics --------------------------------------------------------------------

    @inline
    def sq(x):
        return x * x

    @inline
    def pieces_of(P, b, F_max, s0L, s0R, e0L, e0R, frac):
        """One piece's trapezoidal integrals of slip (lower) and crush (upper) excess squared."""
        FlL, FlR = P[iFlim, b], P[iFlim + 1, b]
        slip = HALF * frac * (sq(max(FlL - s0L, Z0)) + sq(max(FlL - e0L, Z0))) + HALF * frac * (
            sq(max(FlR - s0R, Z0)) + sq(max(FlR - e0R, Z0))
        )
        crush = HALF * frac * (sq(max(s0L - F_max, Z0)) + sq(max(e0L - F_max, Z0))) + HALF * frac * (
            sq(max(s0R - F_max, Z0)) + sq(max(e0R - F_max, Z0))
        )
        return slip, crush

    filippov = step == "filippov"

    # Each loop over a block is a function of its own: LLVM vectorises a loop only if no value it
    # computes is used after it, and in one long function numba keeps every loop's names alive.

    @inline
    def sample_loop(P, S, t, cos_t, sin_t, in_grip, lag_weight, dt):
        """The sample at t_k: forces and the lag (objectives), and the step's setup."""
        (
            y,
            yn,
            rem,
            off,
            onL,
            onR,
            FeL,
            FeR,
            F0L,
            F0R,
            leastL,
            leastR,
            peakL,
            peakR,
            slip,
            crush,
            impact,
            lag,
            diverged,
            t_div,
            hs,
            sLa,
            sRa,
            sfLa,
            sfRa,
            kpL,
            kpR,
        ) = S
        for b in range(P.shape[1]):
            yb = load(y, b)
            FL, FR = forces_at(P, b, yb, False, False, False, False)
            xL = command(P, b, t, cos_t, sin_t, ONE)[2]
            xR = command(P, b, t, cos_t, sin_t, -ONE)[2]
            keep = not diverged[b]
            leastL[b] = min(leastL[b], FL) if (keep and in_grip) else leastL[b]
            leastR[b] = min(leastR[b], FR) if (keep and in_grip) else leastR[b]
            peakL[b] = max(peakL[b], FL) if keep else peakL[b]
            peakR[b] = max(peakR[b], FR) if keep else peakR[b]
            lag[b] = lag[b] + lag_weight * (sq(xL - yb[0]) + sq(xR - yb[1])) if keep else lag[b]
            F0L[b], F0R[b] = FL, FR
            FeL[b], FeR[b] = FL, FR
            rem[b] = dt
            off[b] = Z0
            onL[b] = False
            onR[b] = False
            kpL[b], kpR[b] = -1, -1
            store(yn, b, yb)

    @inline
    def piece_loop(P, S, t, cos_t, sin_t, dt, last, step_in_grip, after, F_max):
        """One piece of the sliding-mode step for every sample of the block, and its path's metrics."""
        (
            y,
            yn,
            rem,
            off,
            onL,
            onR,
            FeL,
            FeR,
            F0L,
            F0R,
            leastL,
            leastR,
            peakL,
            peakR,
            slip,
            crush,
            impact,
            lag,
            diverged,
            t_div,
            hs,
            sLa,
            sRa,
            sfLa,
            sfRa,
            kpL,
            kpR,
        ) = S
        for b in range(P.shape[1]):
            yb = load(yn, b)
            tb, cb, sb = advance(t, cos_t, sin_t, off[b])
            total, h, iL, iR, sfL, sfR, sL, sR, heldL, heldR, k1, k2, k3, k4, slides = substep(
                P, b, yb, tb, cb, sb, rem[b], onL[b], onR[b], kpL[b], kpR[b], dt, last
            )
            new = axpy(yb, h / DEN, total)
            # A crossing the piece held the switch through: the piece ends there, on RK4's continuous
            # extension (filippov.step).
            _, _, kL = geometry(P, 0, b, ONE, new[0], new[2], new[18], new[19])
            _, _, kR = geometry(P, 1, b, -ONE, new[1], new[3], new[18], new[19])
            fL, tL, hL = found(
                heldL[0], heldL[1], heldL[2], heldL[3], heldL[4], heldL[5], heldL[6], kL, P[iFlim, b], h, not last
            )
            fR, tR, hR = found(
                heldR[0], heldR[1], heldR[2], heldR[3], heldR[4], heldR[5], heldR[6], kR, P[iFlim + 1, b], h, not last
            )
            # Or a sliding exit (filippov.sliding_exit), merged per robot as filippov.step does.
            xL, uL, gL = sliding_exit(slides[0], slides[1], slides[2], h)
            xR, uR, gR = sliding_exit(slides[3], slides[4], slides[5], h)
            hL = gL if (xL and uL < (tL if fL else INF)) else hL
            hR = gR if (xR and uR < (tR if fR else INF)) else hR
            tL = min(tL if fL else INF, uL)
            tR = min(tR if fR else INF, uR)
            fL, fR = fL or xL, fR or xR
            h_eff = h
            kL_next, kR_next = -1, -1
            offL, offR = iL, iR
            if fL or fR:
                tau = min(tL if fL else INF, tR if fR else INF)
                th = tau / (h if h > Z0 else ONE)
                b1 = D1[0] * th + D1[1] * th * th + D1[2] * th * th * th
                b23 = D23[0] * th + D23[1] * th * th + D23[2] * th * th * th
                b4 = D4[0] * th + D4[1] * th * th + D4[2] * th * th * th
                new = axpy(yb, h, weighted_dense(k1, k2, k3, k4, b1, b23, b4))
                h_eff = tau
                sfL = fL and tL <= tau and hL >= 0
                sfR = fR and tR <= tau and hR >= 0
                iL, iR = False, False
                kL_next = gL if (xL and uL <= tau) else -1
                kR_next = gR if (xR and uR <= tau) else -1
            kpL[b], kpR[b] = kL_next, kR_next
            eL, eR = forces_at(P, b, new, onL[b], onR[b], offL, offR)
            store(yn, b, new)
            rem[b] = rem[b] - h_eff
            off[b] = off[b] + h_eff
            onL[b], onR[b] = iL, iR
            FeL[b], FeR[b] = eL, eR
            hs[b], sLa[b], sRa[b], sfLa[b], sfRa[b] = h_eff, sL, sR, sfL, sfR
        # The piece's path, in a loop of its own (in the step's loop it kept it from vectorising): the
        # peak at its ends, the means' trapezoids, the least force at a located event (not after the
        # last piece).
        for b in range(P.shape[1]):
            h, sL, sR, eL, eR, iL, iR, sfL, sfR = (
                hs[b],
                sLa[b],
                sRa[b],
                FeL[b],
                FeR[b],
                onL[b],
                onR[b],
                sfLa[b],
                sfRa[b],
            )
            keep = not diverged[b]
            s_, c_ = pieces_of(P, b, F_max, sL, sR, eL, eR, h / dt)
            peakL[b] = max(peakL[b], max(sL, eL)) if keep else peakL[b]
            peakR[b] = max(peakR[b], max(sR, eR)) if keep else peakR[b]
            slip[b] = slip[b] + dt * s_ if (keep and step_in_grip) else slip[b]
            crush[b] = crush[b] + dt * c_ if (keep and step_in_grip) else crush[b]
            impact[b] = impact[b] + dt * c_ if (keep and after) else impact[b]
            evL = eL if iL else (P[iFlim, b] if sfL else INF)
            evR = eR if iR else (P[iFlim + 1, b] if sfR else INF)
            counted = keep and step_in_grip and not last
            leastL[b] = min(leastL[b], evL) if counted else leastL[b]
            leastR[b] = min(leastR[b], evR) if counted else leastR[b]

    @inline
    def busy(rem):
        for b in range(rem.shape[0]):
            if rem[b] > Z0:
                return True
        return False

    @inline
    def rk4_loop(P, S, t, cos_t, sin_t, dt, step_in_grip, after, F_max):
        """A plain RK4 step for every sample of the block, and its path's metrics."""
        (
            y,
            yn,
            rem,
            off,
            onL,
            onR,
            FeL,
            FeR,
            F0L,
            F0R,
            leastL,
            leastR,
            peakL,
            peakR,
            slip,
            crush,
            impact,
            lag,
            diverged,
            t_div,
            hs,
            sLa,
            sRa,
            sfLa,
            sfRa,
            kpL,
            kpR,
        ) = S
        c2, c3, c4 = A2 * dt, A3 * dt, A4 * dt
        t2, cos2, sin2 = advance(t, cos_t, sin_t, c2)
        t3, cos3, sin3 = advance(t, cos_t, sin_t, c3)
        t4, cos4, sin4 = advance(t, cos_t, sin_t, c4)
        dt_den = dt / DEN
        for b in range(P.shape[1]):
            yb = load(y, b)  # equal to yn here; reading one array and writing another
            k1 = hard_field(P, b, yb, t, cos_t, sin_t)
            k2 = hard_field(P, b, axpy(yb, c2, k1), t2, cos2, sin2)
            k3 = hard_field(P, b, axpy(yb, c3, k2), t3, cos3, sin3)
            k4 = hard_field(P, b, axpy(yb, c4, k3), t4, cos4, sin4)
            store(yn, b, axpy(yb, dt_den, weighted(k1, k2, k3, k4)))
        # The metrics in a loop of their own: in the step's loop they kept it from vectorising.
        for b in range(P.shape[1]):
            eL, eR = forces_at(P, b, load(yn, b), False, False, False, False)
            sL, sR = F0L[b], F0R[b]
            keep = not diverged[b]
            s_, c_ = pieces_of(P, b, F_max, sL, sR, eL, eR, ONE)
            peakL[b] = max(peakL[b], max(sL, eL)) if keep else peakL[b]
            peakR[b] = max(peakR[b], max(sR, eR)) if keep else peakR[b]
            slip[b] = slip[b] + dt * s_ if (keep and step_in_grip) else slip[b]
            crush[b] = crush[b] + dt * c_ if (keep and step_in_grip) else crush[b]
            impact[b] = impact[b] + dt * c_ if (keep and after) else impact[b]

    @inline
    def divergence_loop(P, S, t, dt, F_bound):
        """integration/loop.py's rule: a non-finite state or an absurd force at the step's start
        freezes the sample at its last good state."""
        (
            y,
            yn,
            rem,
            off,
            onL,
            onR,
            FeL,
            FeR,
            F0L,
            F0R,
            leastL,
            leastR,
            peakL,
            peakR,
            slip,
            crush,
            impact,
            lag,
            diverged,
            t_div,
            hs,
            sLa,
            sRa,
            sfLa,
            sfRa,
            kpL,
            kpR,
        ) = S
        for b in range(P.shape[1]):
            bad = abs(F0L[b]) > F_bound or abs(F0R[b]) > F_bound
            for r in range(20):
                bad = bad or not math.isfinite(yn[r, b])
            t_div[b] = t + dt if (bad and not diverged[b]) else t_div[b]
            diverged[b] = diverged[b] or bad
            if not diverged[b]:
                for r in range(20):
                    y[r, b] = yn[r, b]

    @jit
    def run_block(P, dt, n, g0, g1, l0, l1, F_bound, F_max, out):
        """One block of the batch over the whole run; writes its metrics (N_METRICS, m) into out."""
        m = P.shape[1]
        S = (
            np.zeros((20, m), P.dtype),
            np.zeros((20, m), P.dtype),
            np.empty(m, P.dtype),
            np.empty(m, P.dtype),
            np.zeros(m, np.bool_),
            np.zeros(m, np.bool_),
            np.empty(m, P.dtype),
            np.empty(m, P.dtype),
            np.empty(m, P.dtype),
            np.empty(m, P.dtype),
            np.full(m, INF, P.dtype),
            np.full(m, INF, P.dtype),
            np.full(m, -INF, P.dtype),
            np.full(m, -INF, P.dtype),
            np.zeros(m, P.dtype),
            np.zeros(m, P.dtype),
            np.zeros(m, P.dtype),
            np.zeros(m, P.dtype),
            np.zeros(m, np.bool_),
            np.full(m, INF, P.dtype),
            np.zeros(m, P.dtype),
            np.zeros(m, P.dtype),
            np.zeros(m, P.dtype),
            np.zeros(m, np.bool_),
            np.zeros(m, np.bool_),
            np.full(m, -1, np.int64),
            np.full(m, -1, np.int64),
        )
        for k in range(n + 1):
            t = T(k) * dt
            cos_t, sin_t = T(math.cos(TWO_PI * t)), T(math.sin(TWO_PI * t))
            step_in_grip = (k >= g0) and (k < g1)
            # The lag's trapezoidal weights over its window (objectives/tracking.py).
            lag_weight = (HALF if (k == l0 or k == l1) else ONE) if (k >= l0 and k <= l1) else Z0
            sample_loop(P, S, t, cos_t, sin_t, (k >= g0) and (k <= g1), lag_weight, dt)
            if k == n:
                break
            if filippov:
                for j in range(PIECES):
                    if j > 0 and not busy(S[2]):
                        break
                    piece_loop(P, S, t, cos_t, sin_t, dt, j == PIECES - 1, step_in_grip, k >= g1, F_max)
            else:
                rk4_loop(P, S, t, cos_t, sin_t, dt, step_in_grip, k >= g1, F_max)
            divergence_loop(P, S, t, dt, F_bound)
        (
            y,
            yn,
            rem,
            off,
            onL,
            onR,
            FeL,
            FeR,
            F0L,
            F0R,
            leastL,
            leastR,
            peakL,
            peakR,
            slip,
            crush,
            impact,
            lag,
            diverged,
            t_div,
            hs,
            sLa,
            sRa,
            sfLa,
            sfRa,
            kpL,
            kpR,
        ) = S
        grip_span = T(max(0, g1 - g0)) * dt
        after_span = T(max(0, n - g1)) * dt
        n_lag = max(0, l1 - l0)
        nan = T(np.nan)
        for b in range(m):
            d = diverged[b]
            out[0, b] = nan if (d or grip_span == Z0) else min(leastL[b], leastR[b])
            out[1, b] = nan if d else max(peakL[b], peakR[b])
            out[2, b] = nan if (d or grip_span == Z0) else slip[b] / grip_span
            out[3, b] = nan if (d or grip_span == Z0) else crush[b] / grip_span
            out[4, b] = nan if (d or after_span == Z0) else impact[b] / after_span
            out[5, b] = nan if (d or n_lag == 0) else math.sqrt(lag[b] / T(2 * n_lag))
            out[6, b] = Z0 if d else ONE
            out[7, b] = t_div[b] if d else nan

    @numba.njit(parallel=True, error_model="numpy", fastmath=False)
    def run(P, dt, n, g0, g1, l0, l1, F_bound, F_max, block):
        """Metrics (N_METRICS, B): blocks in parallel, each over the whole horizon; g0, g1 and l0, l1
        are the inclusive sample windows of grip and lag."""
        B = P.shape[1]
        n_blocks = (B + block - 1) // block
        out = np.empty((N_METRICS, B), P.dtype)
        for c in numba.prange(n_blocks):
            lo = c * block
            hi = min(B, lo + block)
            block_out = np.empty((N_METRICS, hi - lo), P.dtype)
            run_block(np.ascontiguousarray(P[:, lo:hi]), dt, n, g0, g1, l0, l1, F_bound, F_max, block_out)
            out[:, lo:hi] = block_out
        return out

    def metrics(P, dt=1e-3, T_end=4.0, F_bound=1e6, F_max=15.0, block=BLOCK):
        """The carry metrics (N_METRICS, B) of each column of P (`parameter_matrix`), in this dtype."""
        from coopjax import objectives, scenarios

        n = max(1, int(round(T_end / dt)))
        ctx = objectives.Context(scenarios.get("carry"), dt, n)
        (g0, g1), (l0, l1) = ctx.window("grip"), ctx.window("lag")
        P = P if P.dtype == object else np.ascontiguousarray(P, T)  # object: the FLOP count (`count_flops`)
        return run(P, T(dt), n, g0, g1, l0, l1, T(F_bound), T(F_max), int(block))

    return metrics


def agreement(step: str, params, T_end: float, block: int = BLOCK) -> float:
    """The largest relative disagreement of the peer's carry metrics with coopjax's, float64.

    The N^2 means are often round-off (1e-28 N^2 while the grip slides on F_lim): an absolute floor of
    1e-9 N^2. Plain RK4 on the hard switch chatters on F = F_lim and amplifies round-off after the
    first second (two correct transcriptions then part): compare it over that second.
    Under NUMBA_DISABLE_JIT=1 the peer runs as Python, which is how the test suite checks it.
    """
    import coopjax as cj
    from benchmarks.implementations import parameter_matrix

    ours = cj.simulate(params, "carry", integrator=step, T=T_end, check_dt=False, dtype="float64", metrics=OURS).metrics
    theirs = make_peer(step, "float64")(parameter_matrix(params), T_end=T_end, block=block)
    worst = 0.0
    for j, name in enumerate(METRICS):
        a, b = np.asarray(getattr(ours, name), np.float64), theirs[j]
        floor = 1e-9 if name in ("slip", "crush", "impact") else 0.0
        err = np.abs(a - b) / np.maximum(np.abs(a), 1e-300)
        err = np.where(np.abs(a - b) <= floor, 0.0, err)
        err = np.where(np.isnan(a) & np.isnan(b), 0.0, np.where(np.isnan(a) | np.isnan(b), np.inf, err))
        worst = max(worst, float(np.max(err)))
    return worst


# --- what the compiler made of it ---------------------------------------------------------------

_ARITHMETIC = re.compile(r"^\s*v(add|sub|mul|div|sqrt|min|max|cmp\w*|fn?m(?:add|sub)\d+|blendv)([ps])([sd])\s+(.*)$")


def vectorisation(metrics) -> dict:
    """The compiler's own report on a compiled peer (`make_peer`'s result, called once): its block
    kernel's floating-point arithmetic instructions in the machine code, by register: packed in xmm
    (two float64 or four float32), ymm or zmm registers, or scalar; and the share packed in ymm or
    zmm. LLVM's loop vectoriser, run over a block's samples, fills the widest registers the CPU
    has (four to sixteen samples an instruction); packed xmm is mostly LLVM pairing the two robots'
    rows within one sample. LLVM keeps a scalar copy of every loop it vectorises for the block's
    remainder, so a vectorised kernel still shows scalar code."""
    cells = dict(zip(metrics.__code__.co_freevars, (c.cell_contents for c in metrics.__closure__)))
    run = cells["run"]
    kernel = dict(zip(run.py_func.__code__.co_freevars, (c.cell_contents for c in run.py_func.__closure__)))
    run_block = kernel["run_block"]
    counts = {"packed_xmm": 0, "packed_ymm": 0, "packed_zmm": 0, "scalar": 0}
    for signature in run_block.signatures:
        for line in run_block.inspect_asm(signature).splitlines():
            match = _ARITHMETIC.match(line)
            if not match:
                continue
            if match.group(2) == "s":
                counts["scalar"] += 1
            else:
                counts[f"packed_{re.search(r'%([xyz])mm', match.group(4)).group(1)}mm"] += 1
    counts["wide_share"] = (counts["packed_ymm"] + counts["packed_zmm"]) / max(1, sum(counts.values()))
    return counts


def lanes_pair(T_end: float = 4.0, B: int = 4096, repeats: int = 5) -> dict:
    """The sliding-mode peer in float64, plain and with `lanes=True`: instruction counts, their
    largest relative disagreement on 64 random sets, and M sample-steps per second timed in turn."""
    import statistics
    import time

    import coopjax as cj
    from benchmarks.implementations import parameter_matrix

    rng = np.random.default_rng(2)
    check = parameter_matrix(
        cj.make_params(
            M_b=np.exp(rng.uniform(np.log(0.5), np.log(5.0), 64)),
            K_GP=rng.uniform(0.05, 1.5, 64),
            K_GI=rng.uniform(0.01, 0.8, 64),
            tau=rng.uniform(0.2, 4.0, 64),
            G_e=np.exp(rng.uniform(np.log(50.0), np.log(3000.0), 64)),
        )
    )
    rng = np.random.default_rng(0)  # the benchmark's batch
    P = parameter_matrix(cj.make_params(M_b=rng.uniform(0.5, 5.0, B), K_GP=rng.uniform(0.3, 0.7, B)))
    peers = {lanes: make_peer("filippov", "float64", lanes) for lanes in (False, True)}
    report, results, times = {}, {}, {False: [], True: []}
    for lanes, peer in peers.items():
        results[lanes] = peer(check, T_end=T_end)  # compiles it
        report[f"lanes={lanes}"] = vectorisation(peer)
    a, b = results[False], results[True]
    err = np.where(np.abs(a - b) <= 1e-9, 0.0, np.abs(a - b) / np.maximum(np.abs(a), 1e-300))
    report["disagreement"] = float(np.nanmax(err))
    for _ in range(repeats):
        for lanes, peer in peers.items():
            t0 = time.perf_counter()
            peer(P, T_end=T_end)
            times[lanes].append(time.perf_counter() - t0)
    steps = B * int(round(T_end / 1e-3))
    for lanes in peers:
        report[f"lanes={lanes}"]["M_steps_per_s"] = steps / statistics.median(times[lanes]) / 1e6
    return report


# --- the FLOP count of the source ---------------------------------------------------------------


class _Counted:
    """A float that counts the arithmetic done on it: + - * / negation, abs, comparisons (a max,
    min or select is one), sqrt. Run through the kernel's own Python source (NUMBA_DISABLE_JIT)."""

    ops = 0
    __slots__ = ("v",)

    def __init__(self, v):
        self.v = float(v)

    def __float__(self):
        return self.v


def _binary(name, fn):
    def op(a, b):
        _Counted.ops += 1
        return _Counted(fn(float(a), float(b)))

    def rop(a, b):
        _Counted.ops += 1
        return _Counted(fn(float(b), float(a)))

    setattr(_Counted, f"__{name}__", op)
    setattr(_Counted, f"__r{name}__", rop)


def _compare(name, fn):
    def op(a, b):
        _Counted.ops += 1
        return fn(float(a), float(b))

    setattr(_Counted, f"__{name}__", op)


for _name, _fn in (
    ("add", lambda a, b: a + b),
    ("sub", lambda a, b: a - b),
    ("mul", lambda a, b: a * b),
    ("pow", lambda a, b: a**b),
    ("truediv", lambda a, b: a / b if b else math.copysign(math.inf, a) * math.copysign(1.0, b) if a else math.nan),
):
    _binary(_name, _fn)
for _name, _fn in (
    ("lt", lambda a, b: a < b),
    ("le", lambda a, b: a <= b),
    ("gt", lambda a, b: a > b),
    ("ge", lambda a, b: a >= b),
):
    _compare(_name, _fn)


def _unary(a, fn):
    _Counted.ops += 1
    return _Counted(fn(float(a)))


_Counted.__neg__ = lambda a: _unary(a, lambda x: -x)
_Counted.__abs__ = lambda a: _unary(a, abs)


class _CountingMath:
    """`math` for the count: sqrt counts one; the rest (per step, not per sample) as math's."""

    def __getattr__(self, name):
        return getattr(_math, name)

    @staticmethod
    def sqrt(x):
        return _unary(x, lambda v: _math.sqrt(v) if v >= 0 else _math.nan)


def count_flops(step: str, T_end: float = 4.0, B: int = 2, seed: int = 0) -> float:
    """FLOP per sample-step of the peer's source, metrics included, over a carry run of B random
    samples (the sliding-mode step's count depends on how many of its pieces run). Runs the source
    as Python, so it must be called in a process started with NUMBA_DISABLE_JIT=1."""
    import coopjax as cj
    from benchmarks.implementations import parameter_matrix

    global math
    rng = np.random.default_rng(seed)
    P = parameter_matrix(cj.make_params(M_b=rng.uniform(0.5, 5.0, B), K_GP=rng.uniform(0.3, 0.7, B)))
    counted = np.empty(P.shape, object)
    for index, value in np.ndenumerate(P):
        counted[index] = _Counted(value)
    make_peer.cache_clear()
    math = _CountingMath()
    try:
        _Counted.ops = 0
        make_peer(step, "float64")(counted, T_end=T_end, block=B)
    finally:
        math = _math
        make_peer.cache_clear()
    return _Counted.ops / (B * round(T_end / 1e-3))


if __name__ == "__main__":  # python -m benchmarks.strong_peer: the FLOP counts, or the compiler's report (JSON)
    import argparse
    import json
    import os
    import sys

    parser = argparse.ArgumentParser(
        prog="python -m benchmarks.strong_peer",
        description="FLOP per sample-step of the strong peer's source (under NUMBA_DISABLE_JIT=1), or with "
        "--vectorisation what LLVM made of each compiled peer; as JSON",
    )
    parser.add_argument("--T", type=float, default=4.0, help="horizon of the counted carry run, s (default 4)")
    parser.add_argument(
        "--vectorisation",
        action="store_true",
        help="compile the peers (both steps and dtypes, and the sliding-mode step with lanes=True; some 20 "
        "minutes) and count their packed and scalar arithmetic instructions",
    )
    parser.add_argument(
        "--lanes",
        action="store_true",
        help="compile the sliding-mode peer in float64 plain and with lanes=True (some 9 minutes), check "
        "that they agree on 64 random sets, and time them in turn (B = 4096, medians of 5)",
    )
    args = parser.parse_args()
    if (args.vectorisation or args.lanes) and os.environ.get("NUMBA_DISABLE_JIT") == "1":
        print("--vectorisation and --lanes compile the peers: run without NUMBA_DISABLE_JIT=1", file=sys.stderr)
        sys.exit(2)
    if args.lanes:
        print(json.dumps(lanes_pair(T_end=args.T)))
        sys.exit(0)
    if args.vectorisation:
        report = {}
        for step, lanes in (("filippov", False), ("filippov", True), ("rk4", False)):
            for dtype in ("float32", "float64"):
                peer = make_peer(step, dtype, lanes)
                peer(np.ones((46, 2)), T_end=2e-3, block=2)  # compiles it
                report[f"{step}{'_lanes' if lanes else ''}_{dtype}"] = vectorisation(peer)
        print(json.dumps(report))
        sys.exit(0)
    if os.environ.get("NUMBA_DISABLE_JIT") != "1":
        print("run with NUMBA_DISABLE_JIT=1: the count runs the source as Python", file=sys.stderr)
        sys.exit(2)
    print(json.dumps({step: count_flops(step, T_end=args.T) for step in ("filippov", "rk4")}))

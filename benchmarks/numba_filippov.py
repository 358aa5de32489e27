"""The sliding-mode step (coopjax/integration/filippov.py, docs/model.md), written again in numba: the
peer for the throughput benchmark. Carry scenario, unilateral contact, hard switch, alpha_b = 1,
delta0 = 0, with the carry metrics accumulated as coopjax does (objectives.accumulate).

Layout: chunks of the batch run in parallel over the cores (prange), each over the whole horizon;
inside a chunk every loop over the batch is innermost and contiguous, and selects are written as
arithmetic or conditional expressions, not as branches around blocks.
"""

from __future__ import annotations

import math

import numpy as np

from benchmarks.implementations import PER_ROBOT, TWO_PI

EPS = 1e-9  # as coopjax.integration.filippov.EPS
N_METRICS = 8  # min_grip, peak_grip, slip, crush, rms_lag, impact, finite, t_diverged
SWITCHED = (2, 3, 6, 7, 8, 9, 12, 13, 14, 15, 16, 17)  # rows of v_r, v_v, q_c, v_f, Z, Y_e (both robots)


def make_numba_filippov():
    """Compile on first use, so importing this module does not need numba."""
    import numba

    n_per = len(PER_ROBOT)
    base = 2 * n_per
    njit = lambda f=None, **kw: numba.njit(f, fastmath=False, **kw) if f is not None else (lambda g: numba.njit(g, fastmath=False, **kw))

    @njit
    def cos_sin_small(x):
        x2 = x * x
        c = 1.0 - x2 / 2 * (1 - x2 / 12 * (1 - x2 / 30 * (1 - x2 / 56 * (1 - x2 / 90))))
        s = x * (1.0 - x2 / 6 * (1 - x2 / 20 * (1 - x2 / 42 * (1 - x2 / 72 * (1 - x2 / 110)))))
        return c, s

    @njit(inline="always")
    def bump(t, cos, sin, t0, A):
        u = t - t0
        inside = (u >= 0.0) and (u < 1.0)
        v = A * (1.0 - cos) if inside else 0.0
        a = A * TWO_PI * sin if inside else 0.0
        x = 0.0 if u < 0.0 else (A * (u - sin / TWO_PI) if inside else A)
        return v, a, x

    @njit(inline="always")
    def command(t, cos, sin, s, A_g, A_c):
        v1, a1, x1 = bump(t, cos, sin, 0.0, s * A_g)
        v2, a2, x2 = bump(t, cos, sin, 1.0, A_c)
        v3, a3, x3 = bump(t, cos, sin, 2.0, -2.0 * s * A_g)
        return v1 + v2 + v3, a1 + a2 + a3, x1 + x2 + x3

    @njit(inline="always")
    def robot_rates(P, i, b, s, y, F, w, F_gamma, F_memory, v_cmd, a_cmd, x_ref):
        """Robot i's nine rates at sample b for a numeric switch value w (0 or 1)."""
        M_v, M_r = P[0 + i, b], P[2 + i, b]
        M_c, R_c, K_c, M_f = P[8 + i, b], P[10 + i, b], P[12 + i, b], P[14 + i, b]
        R_f, K_f, mu_H, beta_H = P[16 + i, b], P[18 + i, b], P[20 + i, b], P[22 + i, b]
        F_lim, K_ini, K_GP, K_GI = P[24 + i, b], P[26 + i, b], P[28 + i, b], P[30 + i, b]
        tau, tau_e, G_e, rho = P[32 + i, b], P[34 + i, b], P[36 + i, b], P[38 + i, b]
        x_r, v_r, v_v = y[i, b], y[2 + i, b], y[6 + i, b]
        q_c, x_f, v_f, Z, Y_e = y[8 + i, b], y[10 + i, b], y[12 + i, b], y[14 + i, b], y[16 + i, b]
        off = 1.0 - w
        gamma = 1.0 - w * (K_ini + K_GP * (F_gamma - F_lim) + K_GI * Z)
        dZ = w * (F_memory - F_lim) - tau * Z - off * rho * Z
        dY = off * (x_ref - x_r) - tau_e * Y_e - w * rho * Y_e
        v_ref = v_cmd + off * G_e * Y_e
        a_ref = a_cmd + off * G_e * dY
        g = (1.0 - gamma) * beta_H
        err = v_ref - v_r - g * v_f
        D = M_c * a_ref + R_c * err + K_c * q_c
        h = R_f * v_f + K_f * x_f
        f_ext = -s * F
        e_c = (D - M_c * f_ext / M_r + M_c * g * h / M_f) / (1.0 + M_c * mu_H / M_r + M_c * g / M_f)
        return (v_r, (mu_H * e_c + f_ext) / M_r, v_v, -mu_H * e_c / M_v, err, v_f, (e_c - h) / M_f, dZ, dY)

    @njit(inline="always")
    def in_contact(y, on, off_, i, b):
        s = 1.0 if i == 0 else -1.0
        delta = s * (y[i, b] - y[18, b])
        return on[i, b] > 0.5 or (not (off_[i, b] > 0.5) and delta > 0.0)

    @njit(inline="always")
    def contact_force(P, y, on, off_, i, b):
        s = 1.0 if i == 0 else -1.0
        delta = s * (y[i, b] - y[18, b])
        delta_dot = s * (y[2 + i, b] - y[19, b])
        kel = P[4 + i, b] * delta + P[6 + i, b] * delta_dot
        return max(kel, 0.0) if in_contact(y, on, off_, i, b) else 0.0

    @njit
    def stage(P, y, t, cos, sin, sigma_n, h, on, off_, k, F_start):
        """One RK4 stage of the sliding-mode step: rates k (20, m) at y, Filippov weight per robot.

        t, cos, sin, h: per sample (m,); sigma_n (2, m) at the substep start; on/off_ (2, m) contact
        overrides as 0/1 floats. F_start receives the contact force (2, m).
        """
        m = y.shape[1]
        for b in range(m):
            F_L = contact_force(P, y, on, off_, 0, b)
            F_R = contact_force(P, y, on, off_, 1, b)
            F_start[0, b] = F_L
            F_start[1, b] = F_R
            F = (F_L, F_R)
            a_o = (F_L - F_R) / P[base, b]
            k[18, b] = y[19, b]
            k[19, b] = a_o
            for i in range(2):
                s = 1.0 if i == 0 else -1.0
                v_cmd, a_cmd, x_ref = command(t[b], cos[b], sin[b], s, P[base + 1, b], P[base + 2, b])
                F_lim = P[24 + i, b]
                clamped = max(F[i], F_lim)
                r0 = robot_rates(P, i, b, s, y, F[i], 0.0, F[i], F[i], v_cmd, a_cmd, x_ref)
                r1 = robot_rates(P, i, b, s, y, F[i], 1.0, clamped, clamped, v_cmd, a_cmd, x_ref)
                delta_dot = s * (y[2 + i, b] - y[19, b])
                sd0 = P[4 + i, b] * delta_dot + P[6 + i, b] * s * (r0[1] - a_o)
                sd1 = P[4 + i, b] * delta_dot + P[6 + i, b] * s * (r1[1] - a_o)
                d = sd0 - sd1
                sliding = d > EPS
                lam_star = min(max(sd0 / d, 0.0), 1.0) if sliding else (1.0 if sd0 >= 0.0 else 0.0)
                sn = sigma_n[i, b]
                below = sd0 * h[b] > 0.0
                theta_b = min(max(-sn / (sd0 * h[b]), 0.0), 1.0) if below else 1.0
                above = -sd1 * h[b] > 0.0
                theta_a = min(max(sn / (-sd1 * h[b]), 0.0), 1.0) if above else 1.0
                lam = (1.0 - theta_b) * lam_star if sn < 0.0 else theta_a + (1.0 - theta_a) * lam_star
                lam = lam if in_contact(y, on, off_, i, b) else 0.0
                k[i, b] = r0[0]
                k[2 + i, b] = r0[1] + lam * (r1[1] - r0[1])
                k[4 + i, b] = r0[2]
                k[6 + i, b] = r0[3] + lam * (r1[3] - r0[3])
                k[8 + i, b] = r0[4] + lam * (r1[4] - r0[4])
                k[10 + i, b] = r0[5]
                k[12 + i, b] = r0[6] + lam * (r1[6] - r0[6])
                k[14 + i, b] = r0[7] + lam * (r1[7] - r0[7])
                k[16 + i, b] = r0[8] + lam * (r1[8] - r0[8])

    @njit
    def sigma_at(P, y, on, off_, out):
        m = y.shape[1]
        for b in range(m):
            for i in range(2):
                s = 1.0 if i == 0 else -1.0
                delta = s * (y[i, b] - y[18, b])
                delta_dot = s * (y[2 + i, b] - y[19, b])
                kel = P[4 + i, b] * delta + P[6 + i, b] * delta_dot
                c = on[i, b] > 0.5 or (not (off_[i, b] > 0.5) and delta > 0.0)
                out[i, b] = (kel if c else 0.0) - P[24 + i, b]

    @njit
    def substep(P, y, t, cos, sin, h, on, off_, ws):
        """RK4 over per-sample length h with the Filippov weight at every stage; y is updated in place.
        Returns nothing; ws holds scratch arrays; ws.F1 the force at the first stage."""
        m = y.shape[1]
        sigma_n, k, total, tmp, F1, Fs = ws[0], ws[1], ws[2], ws[3], ws[4], ws[5]
        tt, cc, ss = ws[6], ws[7], ws[8]
        sigma_at(P, y, on, off_, sigma_n[:2])
        stage(P, y, t, cos, sin, sigma_n[:2], h, on, off_, k, F1[:2])
        for r in range(20):
            for b in range(m):
                total[r, b] = k[r, b]
        for a, wgt in ((0.5, 2.0), (0.5, 2.0), (1.0, 1.0)):
            for r in range(20):
                for b in range(m):
                    tmp[r, b] = y[r, b] + (a * h[b]) * k[r, b]
            for b in range(m):
                c, s_ = cos_sin_small(TWO_PI * (a * h[b]))
                tt[0, b] = t[b] + a * h[b]
                cc[0, b] = cos[b] * c - sin[b] * s_
                ss[0, b] = sin[b] * c + cos[b] * s_
            stage(P, tmp, tt[0], cc[0], ss[0], sigma_n[:2], h, on, off_, k, Fs[:2])
            for r in range(20):
                for b in range(m):
                    total[r, b] = total[r, b] + wgt * k[r, b]
        for r in range(20):
            for b in range(m):
                y[r, b] = y[r, b] + (h[b] / 6) * total[r, b]

    @numba.njit(parallel=True, fastmath=False)
    def run(P, dt, n_steps, grip, lag, F_bound, chunk):
        """Metrics (N_METRICS, B) of the carry scenario from rest; grip and lag are inclusive step
        windows (objectives.window)."""
        B = P.shape[1]
        n_chunks = (B + chunk - 1) // chunk
        out = np.empty((N_METRICS, B))
        n_grip = max(0, grip[1] - grip[0] + 1)
        n_lag = max(0, lag[1] - lag[0] + 1)
        n_after = max(0, n_steps - grip[1])
        for c in numba.prange(n_chunks):
            lo = c * chunk
            hi = min(B, lo + chunk)
            m = hi - lo
            Pc = np.ascontiguousarray(P[:, lo:hi])
            y = np.zeros((20, m))
            y_new = np.empty((20, m))
            ws = np.empty((9, 20, m))
            F = np.empty((2, m))
            on1 = np.zeros((2, m))
            off1 = np.zeros((2, m))
            on2 = np.zeros((2, m))
            off2 = np.zeros((2, m))
            t1 = np.empty(m)
            c1 = np.empty(m)
            s1 = np.empty(m)
            t2 = np.empty(m)
            c2 = np.empty(m)
            s2 = np.empty(m)
            h1 = np.empty(m)
            h2 = np.empty(m)
            Fi = np.empty((2, m))
            acc_min = np.full((2, m), np.inf)
            acc_peak = np.full((2, m), -np.inf)
            slip = np.zeros(m)
            crush = np.zeros(m)
            lag_sq = np.zeros(m)
            impact = np.zeros(m)
            diverged = np.zeros(m, np.bool_)
            t_div = np.full(m, np.inf)
            for k in range(n_steps + 1):
                t = k * dt
                cos_t, sin_t = math.cos(TWO_PI * t), math.sin(TWO_PI * t)
                last = k == n_steps
                for b in range(m):
                    # Forces and the reference at the step start (objectives.accumulate), the impact prediction.
                    F_L = max(Pc[4, b] * (y[0, b] - y[18, b]) + Pc[6, b] * (y[2, b] - y[19, b]), 0.0) \
                        if y[0, b] - y[18, b] > 0.0 else 0.0
                    F_R = max(Pc[5, b] * -(y[1, b] - y[18, b]) + Pc[7, b] * -(y[3, b] - y[19, b]), 0.0) \
                        if -(y[1, b] - y[18, b]) > 0.0 else 0.0
                    F[0, b] = F_L
                    F[1, b] = F_R
                    a_o = (F_L - F_R) / Pc[base, b]
                    step_slip = 0.0
                    step_crush = 0.0
                    step_lag = 0.0
                    step_impact = 0.0
                    theta_c = 1.0
                    frac_L = 2.0
                    frac_R = 2.0
                    for i in range(2):
                        s = 1.0 if i == 0 else -1.0
                        Fk = F_L if i == 0 else F_R
                        v_cmd, a_cmd, x_ref = command(t, cos_t, sin_t, s, Pc[base + 1, b], Pc[base + 2, b])
                        r0 = robot_rates(Pc, i, b, s, y, Fk, 0.0, Fk, Fk, v_cmd, a_cmd, x_ref)
                        F_lim = Pc[24 + i, b]
                        in_grip = k >= grip[0] and k <= grip[1]
                        step_slip += max(F_lim - Fk, 0.0) ** 2 if in_grip else 0.0
                        step_crush += max(Fk - 15.0, 0.0) ** 2 if in_grip else 0.0
                        if in_grip and not diverged[b]:
                            acc_min[i, b] = min(acc_min[i, b], Fk)
                        step_lag += (x_ref - y[i, b]) ** 2
                        step_impact += max(Fk - 15.0, 0.0) ** 2
                        # "Impacts" (docs/model.md): the contact time from the contact-free field.
                        delta = s * (y[i, b] - y[18, b])
                        delta_dot = s * (y[2 + i, b] - y[19, b])
                        ddd = s * (r0[1] - a_o)
                        disc = delta_dot * delta_dot - 2.0 * ddd * delta
                        real = delta <= 0.0 and disc > 0.0
                        den = delta_dot + math.sqrt(disc if real else 1.0)
                        hits = real and den > 0.0
                        tau_c = -2.0 * delta / (den if hits else 1.0)
                        hits = hits and tau_c <= dt
                        fraction = tau_c / dt if hits else 1.0
                        if i == 0:
                            frac_L = fraction if hits else 2.0
                        else:
                            frac_R = fraction if hits else 2.0
                        theta_c = min(theta_c, fraction)
                    if not diverged[b]:
                        in_lag = 1.0 if (k >= lag[0] and k <= lag[1]) else 0.0
                        after = 1.0 if k > grip[1] else 0.0
                        slip[b] += step_slip
                        crush[b] += step_crush
                        lag_sq[b] += in_lag * step_lag
                        impact[b] += after * step_impact
                    first_L = frac_L <= theta_c
                    first_R = frac_R <= theta_c
                    on1[0, b] = 0.0
                    on1[1, b] = 0.0
                    off1[0, b] = 1.0 if first_L else 0.0
                    off1[1, b] = 1.0 if first_R else 0.0
                    on2[0, b] = off1[0, b]
                    on2[1, b] = off1[1, b]
                    off2[0, b] = 0.0
                    off2[1, b] = 0.0
                    h1[b] = theta_c * dt
                    h2[b] = dt - h1[b]
                    t1[b] = t
                    c1[b] = cos_t
                    s1[b] = sin_t
                    cc, ss = cos_sin_small(TWO_PI * h1[b])
                    t2[b] = t + h1[b]
                    c2[b] = cos_t * cc - sin_t * ss
                    s2[b] = sin_t * cc + cos_t * ss
                if last:
                    # The final sample, t_N = T: objectives.accumulate with k = n (observe's F).
                    for b in range(m):
                        if not diverged[b]:
                            for i in range(2):
                                acc_peak[i, b] = max(acc_peak[i, b], F[i, b])
                    break
                for r in range(20):
                    for b in range(m):
                        y_new[r, b] = y[r, b]
                substep(Pc, y_new, t1, c1, s1, h1, on1, off1, ws)
                substep(Pc, y_new, t2, c2, s2, h2, on2, off2, ws)
                for b in range(m):
                    Fi[0, b] = ws[4][0, b]
                    Fi[1, b] = ws[4][1, b]
                for b in range(m):
                    if not diverged[b]:
                        for i in range(2):
                            acc_peak[i, b] = max(acc_peak[i, b], max(F[i, b], Fi[i, b]))
                    bad = abs(F[0, b]) > F_bound or abs(F[1, b]) > F_bound
                    for r in range(20):
                        bad = bad or not math.isfinite(y_new[r, b])
                    if bad and not diverged[b]:
                        t_div[b] = t + dt
                        diverged[b] = True
                    if not diverged[b]:
                        for r in range(20):
                            y[r, b] = y_new[r, b]
            for b in range(m):
                nan = np.nan
                d = diverged[b]
                mn = min(acc_min[0, b] if not math.isinf(acc_min[0, b]) else acc_peak[0, b],
                         acc_min[1, b] if not math.isinf(acc_min[1, b]) else acc_peak[1, b])
                out[0, lo + b] = nan if d or n_grip == 0 else mn
                out[1, lo + b] = nan if d else max(acc_peak[0, b], acc_peak[1, b])
                out[2, lo + b] = nan if d or n_grip == 0 else slip[b] / n_grip
                out[3, lo + b] = nan if d or n_grip == 0 else crush[b] / n_grip
                out[4, lo + b] = nan if d or n_lag == 0 else math.sqrt(lag_sq[b] / (2 * n_lag))
                out[5, lo + b] = nan if d or n_after == 0 else impact[b] / n_after
                out[6, lo + b] = 0.0 if d else 1.0
                out[7, lo + b] = t_div[b] if d else nan
        return out

    def metrics(P, dt=1e-3, T=4.0, chunk=64, F_bound=1e6):
        """The carry metrics of each column of P (from `parameter_matrix`), float64."""
        from coopjax import objectives, scenarios

        n = max(1, int(round(T / dt)))
        ctx = objectives.Context(scenarios.get("carry"), dt, n)
        return run(np.ascontiguousarray(P, np.float64), float(dt), n, np.array(ctx.window("grip")),
                   np.array(ctx.window("lag")), float(F_bound), int(chunk))

    return metrics

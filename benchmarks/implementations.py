"""The carry scenario written the ways a user would write it without coopjax.

Each is an independent transcription of the model and the carry scenario (docs/model.md) (unilateral contact, hard or
smooth switch, full base compensation alpha_b = 1, delta0 = 0). The state layout is coopjax's:
rows 2q and 2q + 1 are quantity q of robots L and R, in the order x_r, v_r, x_v, v_v, q_c, x_f, v_f,
Z, Y_e, then x_o and v_o.

- `numpy_rk4`: classical RK4, vectorised over the batch with NumPy arrays of shape (B,).
- `make_numba_rk4()`: the same RK4 compiled by numba. Chunks of the batch run in parallel over the
  cores, each over the whole horizon; inside a chunk the batch is the inner, contiguous loop.
- `lsoda`: `scipy.integrate.solve_ivp(method="LSODA")` on a scalar right-hand side, once per set.
"""

from __future__ import annotations

import math

import numpy as np

# Per-robot parameters, then shared ones: the order of the rows of the parameter matrix P.
PER_ROBOT = (
    "M_v",
    "M_r",
    "K_g",
    "R_g",
    "M_c",
    "R_c",
    "K_c",
    "M_f",
    "R_f",
    "K_f",
    "mu_H",
    "beta_H",
    "F_lim",
    "K_ini",
    "K_GP",
    "K_GI",
    "tau",
    "tau_e",
    "G_e",
    "rho",
)
SHARED = ("M_b", "A_g", "A_c", "k_F", "k_c", "eps_delta")
TWO_PI = 2.0 * math.pi


def parameter_matrix(params) -> np.ndarray:
    """coopjax Params (batch shape (B,)) -> P of shape (2 * 20 + 6, B), float64, C-contiguous."""
    rows = []
    for name in PER_ROBOT:
        value = np.asarray(getattr(params, name), np.float64)
        rows += [value[0], value[1]]
    rows += [np.asarray(getattr(params, name), np.float64) for name in SHARED]
    return np.ascontiguousarray(np.stack(rows))


def carry_command(t: float, s: float, A_g, A_c):
    """(v_cmd, a_cmd, x_ref) of one robot with sign s at time t: three rest-to-rest bumps."""
    v = a = x = 0.0 * A_g
    for t0, A in ((0.0, s * A_g), (1.0, A_c), (2.0, -2.0 * s * A_g)):
        u = t - t0
        if 0.0 <= u < 1.0:
            c, sn = math.cos(TWO_PI * u), math.sin(TWO_PI * u)
            v = v + A * (1.0 - c)
            a = a + A * TWO_PI * sn
            x = x + A * (u - sn / TWO_PI)
        elif u >= 1.0:
            x = x + A
    return v, a, x


# ----------------------------------------------------------------------------------------------
# NumPy, vectorised over the batch


def _sigmoid(x):
    return 0.5 * (1.0 + np.tanh(0.5 * x))


def numpy_field(P, y, t, smooth: bool):
    """dy/dt for a batch: y (20, B), P from `parameter_matrix`. Also returns the forces (2, B)."""
    p = {name: P[2 * i : 2 * i + 2] for i, name in enumerate(PER_ROBOT)}
    base = 2 * len(PER_ROBOT)
    q = {name: P[base + j] for j, name in enumerate(SHARED)}
    dy = np.empty_like(y)
    x_o, v_o = y[18], y[19]
    forces = np.empty((2,) + y.shape[1:])
    for i, s in enumerate((1.0, -1.0)):
        x_r, v_r, v_v, q_c, x_f, v_f, Z, Y_e = (y[2 * k + i] for k in (0, 1, 3, 4, 5, 6, 7, 8))
        r = {name: value[i] for name, value in p.items()}
        delta, delta_dot = s * (x_r - x_o), s * (v_r - v_o)
        kelvin = r["K_g"] * delta + r["R_g"] * delta_dot
        if smooth:
            F = q["k_c"] * np.logaddexp(0.0, kelvin / q["k_c"]) * _sigmoid(delta / q["eps_delta"])
            w = _sigmoid((F - r["F_lim"]) / q["k_F"])
        else:
            F = np.where(delta > 0.0, np.maximum(kelvin, 0.0), 0.0)
            w = (F >= r["F_lim"]).astype(y.dtype)
        forces[i] = F
        gamma = 1.0 - w * (r["K_ini"] + r["K_GP"] * (F - r["F_lim"]) + r["K_GI"] * Z)
        v_cmd, a_cmd, x_ref = carry_command(t, s, q["A_g"], q["A_c"])
        dY = (1.0 - w) * (x_ref - x_r) - r["tau_e"] * Y_e - w * r["rho"] * Y_e
        v_ref = v_cmd + (1.0 - w) * r["G_e"] * Y_e
        a_ref = a_cmd + (1.0 - w) * r["G_e"] * dY
        g = (1.0 - gamma) * r["beta_H"]
        err = v_ref - v_r - g * v_f
        D = r["M_c"] * a_ref + r["R_c"] * err + r["K_c"] * q_c
        h = r["R_f"] * v_f + r["K_f"] * x_f
        f_ext = -s * F
        e_c = (D - r["M_c"] * f_ext / r["M_r"] + r["M_c"] * g * h / r["M_f"]) / (
            1.0 + r["M_c"] * r["mu_H"] / r["M_r"] + r["M_c"] * g / r["M_f"]
        )
        rates = (
            v_r,
            (r["mu_H"] * e_c + f_ext) / r["M_r"],
            v_v,
            -r["mu_H"] * e_c / r["M_v"],
            err,
            v_f,
            (e_c - h) / r["M_f"],
            w * (F - r["F_lim"]) - r["tau"] * Z - (1.0 - w) * r["rho"] * Z,
            dY,
        )
        for k, rate in enumerate(rates):
            dy[2 * k + i] = rate
    dy[18] = v_o
    dy[19] = (forces[0] - forces[1]) / q["M_b"]
    return dy, forces


def numpy_rk4(P, dt: float, n_steps: int, every: int, smooth: bool = False):
    """RK4 from rest; returns the forces every `every` steps, shape (n_steps // every + 1, 2, B)."""
    y = np.zeros((20, P.shape[1]))
    records = []
    for k in range(n_steps + 1):
        t = k * dt
        k1, F = numpy_field(P, y, t, smooth)
        if k % every == 0:
            records.append(F)
        if k == n_steps:
            break
        k2 = numpy_field(P, y + 0.5 * dt * k1, t + 0.5 * dt, smooth)[0]
        k3 = numpy_field(P, y + 0.5 * dt * k2, t + 0.5 * dt, smooth)[0]
        k4 = numpy_field(P, y + dt * k3, t + dt, smooth)[0]
        y = y + (dt / 6.0) * (k1 + 2.0 * k2 + 2.0 * k3 + k4)
    return np.stack(records)


# ----------------------------------------------------------------------------------------------
# numba: the batch is the inner loop


def make_numba_rk4():
    """Compile on first use, so importing this module does not need numba."""
    import numba

    n_per = len(PER_ROBOT)

    @numba.njit
    def unit_bumps(t):
        """Velocity, acceleration and displacement of the three bumps at unit amplitude: (3, 3)."""
        out = np.zeros((3, 3))
        for j in range(3):
            u = t - 1.0 * j
            if u >= 0.0 and u < 1.0:
                c = math.cos(TWO_PI * u)
                sn = math.sin(TWO_PI * u)
                out[j, 0] = 1.0 - c
                out[j, 1] = TWO_PI * sn
                out[j, 2] = u - sn / TWO_PI
            elif u >= 1.0:
                out[j, 2] = 1.0
        return out

    @numba.njit(fastmath=False)
    def field(P, y, t, smooth, dy, F_out):
        """dy/dt for one chunk of the batch; every loop over the batch is innermost and contiguous."""
        unit = unit_bumps(t)  # the trigonometry depends on t only: once per call, not per sample
        base = 2 * n_per
        m = y.shape[1]
        for i in range(2):
            s = 1.0 if i == 0 else -1.0
            for b in range(m):
                grip, carry = s * P[base + 1, b], P[base + 2, b]  # bumps: s A_g, A_c, -2 s A_g
                v_cmd = grip * unit[0, 0] + carry * unit[1, 0] - 2.0 * grip * unit[2, 0]
                a_cmd = grip * unit[0, 1] + carry * unit[1, 1] - 2.0 * grip * unit[2, 1]
                x_ref = grip * unit[0, 2] + carry * unit[1, 2] - 2.0 * grip * unit[2, 2]
                M_v, M_r, K_g, R_g = P[0 + i, b], P[2 + i, b], P[4 + i, b], P[6 + i, b]
                M_c, R_c, K_c, M_f = P[8 + i, b], P[10 + i, b], P[12 + i, b], P[14 + i, b]
                R_f, K_f, mu_H, beta_H = P[16 + i, b], P[18 + i, b], P[20 + i, b], P[22 + i, b]
                F_lim, K_ini, K_GP, K_GI = P[24 + i, b], P[26 + i, b], P[28 + i, b], P[30 + i, b]
                tau, tau_e, G_e, rho = P[32 + i, b], P[34 + i, b], P[36 + i, b], P[38 + i, b]
                k_F, k_c, eps = P[base + 3, b], P[base + 4, b], P[base + 5, b]
                x_r, v_r, v_v = y[i, b], y[2 + i, b], y[6 + i, b]
                q_c, x_f, v_f, Z, Y_e = y[8 + i, b], y[10 + i, b], y[12 + i, b], y[14 + i, b], y[16 + i, b]
                delta = s * (x_r - y[18, b])
                delta_dot = s * (v_r - y[19, b])
                kelvin = K_g * delta + R_g * delta_dot
                if smooth:
                    z = kelvin / k_c
                    sp = max(z, 0.0) + math.log1p(math.exp(-abs(z)))
                    F = k_c * sp * 0.5 * (1.0 + math.tanh(0.5 * delta / eps))
                    w = 0.5 * (1.0 + math.tanh(0.5 * (F - F_lim) / k_F))
                else:
                    F = max(kelvin, 0.0) if delta > 0.0 else 0.0
                    w = 1.0 if F >= F_lim else 0.0
                F_out[i, b] = F
                gamma = 1.0 - w * (K_ini + K_GP * (F - F_lim) + K_GI * Z)
                dY = (1.0 - w) * (x_ref - x_r) - tau_e * Y_e - w * rho * Y_e
                v_ref = v_cmd + (1.0 - w) * G_e * Y_e
                a_ref = a_cmd + (1.0 - w) * G_e * dY
                g = (1.0 - gamma) * beta_H
                err = v_ref - v_r - g * v_f
                D = M_c * a_ref + R_c * err + K_c * q_c
                h = R_f * v_f + K_f * x_f
                f_ext = -s * F
                e_c = (D - M_c * f_ext / M_r + M_c * g * h / M_f) / (1.0 + M_c * mu_H / M_r + M_c * g / M_f)
                dy[i, b] = v_r
                dy[2 + i, b] = (mu_H * e_c + f_ext) / M_r
                dy[4 + i, b] = v_v
                dy[6 + i, b] = -mu_H * e_c / M_v
                dy[8 + i, b] = err
                dy[10 + i, b] = v_f
                dy[12 + i, b] = (e_c - h) / M_f
                dy[14 + i, b] = w * (F - F_lim) - tau * Z - (1.0 - w) * rho * Z
                dy[16 + i, b] = dY
        for b in range(m):
            dy[18, b] = y[19, b]
            dy[19, b] = (F_out[0, b] - F_out[1, b]) / P[base, b]

    @numba.njit(fastmath=False)
    def axpy(y, k, c, out):
        for r in range(y.shape[0]):
            for b in range(y.shape[1]):
                out[r, b] = y[r, b] + c * k[r, b]

    @numba.njit(parallel=True, fastmath=False)
    def rk4(P, dt, n_steps, every, smooth, chunk):
        """Each thread integrates its own chunks of the batch over the whole horizon: one parallel
        region per call, and the samples of a chunk stay in cache."""
        B = P.shape[1]
        n_chunks = (B + chunk - 1) // chunk
        records = np.zeros((n_steps // every + 1, 2, B))
        for c in numba.prange(n_chunks):
            lo = c * chunk
            hi = min(B, lo + chunk)
            m = hi - lo
            Pc = np.ascontiguousarray(P[:, lo:hi])
            y = np.zeros((20, m))
            k1 = np.empty((20, m))
            k2 = np.empty((20, m))
            k3 = np.empty((20, m))
            k4 = np.empty((20, m))
            tmp = np.empty((20, m))
            F = np.empty((2, m))
            scratch = np.empty((2, m))
            for k in range(n_steps + 1):
                t = k * dt
                field(Pc, y, t, smooth, k1, F)
                if k % every == 0:
                    records[k // every, :, lo:hi] = F
                if k == n_steps:
                    break
                axpy(y, k1, 0.5 * dt, tmp)
                field(Pc, tmp, t + 0.5 * dt, smooth, k2, scratch)
                axpy(y, k2, 0.5 * dt, tmp)
                field(Pc, tmp, t + 0.5 * dt, smooth, k3, scratch)
                axpy(y, k3, dt, tmp)
                field(Pc, tmp, t + dt, smooth, k4, scratch)
                for r in range(20):
                    for b in range(m):
                        y[r, b] += (dt / 6.0) * (k1[r, b] + 2.0 * k2[r, b] + 2.0 * k3[r, b] + k4[r, b])
        return records

    def run(P, dt, n_steps, every, smooth=False, chunk=256):
        return rk4(np.ascontiguousarray(P, np.float64), float(dt), int(n_steps), int(every), bool(smooth), int(chunk))

    return run


# ----------------------------------------------------------------------------------------------
# LSODA on a scalar right-hand side, one parameter set at a time


def scalar_rhs(p: dict, smooth: bool):
    """A right-hand side of plain Python floats for one parameter set (robots L and R equal)."""

    def sig(x):
        return 0.5 * (1.0 + math.tanh(0.5 * x))

    def force(y):
        out = []
        for i, s in enumerate((1.0, -1.0)):
            delta = s * (y[i] - y[18])
            kelvin = p["K_g"] * delta + p["R_g"] * s * (y[2 + i] - y[19])
            if smooth:
                z = kelvin / p["k_c"]
                out.append(p["k_c"] * (max(z, 0.0) + math.log1p(math.exp(-abs(z)))) * sig(delta / p["eps_delta"]))
            else:
                out.append(max(kelvin, 0.0) if delta > 0.0 else 0.0)
        return out

    def rhs(t, y):
        dy = np.empty(20)
        F = force(y)
        for i, s in enumerate((1.0, -1.0)):
            x_r, v_r, v_v, q_c, x_f, v_f, Z, Y_e = (y[2 * k + i] for k in (0, 1, 3, 4, 5, 6, 7, 8))
            w = sig((F[i] - p["F_lim"]) / p["k_F"]) if smooth else (1.0 if F[i] >= p["F_lim"] else 0.0)
            gamma = 1.0 - w * (p["K_ini"] + p["K_GP"] * (F[i] - p["F_lim"]) + p["K_GI"] * Z)
            v_cmd, a_cmd, x_ref = carry_command(t, s, p["A_g"], p["A_c"])
            dY = (1.0 - w) * (x_ref - x_r) - p["tau_e"] * Y_e - w * p["rho"] * Y_e
            v_ref = v_cmd + (1.0 - w) * p["G_e"] * Y_e
            a_ref = a_cmd + (1.0 - w) * p["G_e"] * dY
            g = (1.0 - gamma) * p["beta_H"]
            err = v_ref - v_r - g * v_f
            D = p["M_c"] * a_ref + p["R_c"] * err + p["K_c"] * q_c
            h = p["R_f"] * v_f + p["K_f"] * x_f
            f_ext = -s * F[i]
            e_c = (D - p["M_c"] * f_ext / p["M_r"] + p["M_c"] * g * h / p["M_f"]) / (
                1.0 + p["M_c"] * p["mu_H"] / p["M_r"] + p["M_c"] * g / p["M_f"]
            )
            rates = (
                v_r,
                (p["mu_H"] * e_c + f_ext) / p["M_r"],
                v_v,
                -p["mu_H"] * e_c / p["M_v"],
                err,
                v_f,
                (e_c - h) / p["M_f"],
                w * (F[i] - p["F_lim"]) - p["tau"] * Z - (1.0 - w) * p["rho"] * Z,
                dY,
            )
            for k, rate in enumerate(rates):
                dy[2 * k + i] = rate
        dy[18] = y[19]
        dy[19] = (F[0] - F[1]) / p["M_b"]
        return dy

    return rhs, force


def lsoda(p: dict, T: float, t_eval, smooth: bool = False, rtol: float = 1e-8, atol: float = 1e-10):
    """Forces at t_eval, shape (len(t_eval), 2), from solve_ivp(LSODA), and the number of RHS calls."""
    from scipy.integrate import solve_ivp

    rhs, force = scalar_rhs(p, smooth)
    # max_step: the commands switch on and off at whole seconds, inside which LSODA would step over
    # the start of a bump; 0.1 s is below every command's time scale.
    sol = solve_ivp(rhs, (0.0, T), np.zeros(20), method="LSODA", t_eval=t_eval, rtol=rtol, atol=atol, max_step=0.1)
    if not sol.success:
        raise RuntimeError(f"LSODA failed: {sol.message}")
    return np.array([force(y) for y in sol.y.T]), sol.nfev

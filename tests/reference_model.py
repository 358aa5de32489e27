"""An independent NumPy transcription of the model and its scenarios (docs/model.md; smooth and blend modes),
for solve_ivp.

Written from the specification, not from coopjax's code: scalar per-robot loops, the e_c solve done
as an explicit 3x3 linear system, its own command profiles.
"""

import math

import numpy as np

TABLE1 = dict(
    M_v=10.0,
    M_r=1.0,
    K_g=1000.0,
    R_g=100.0,
    M_c=10.0,
    R_c=5.0,
    K_c=500.0,
    M_f=1.0,
    R_f=200.0,
    K_f=10.0,
    mu_H=300.0,
    beta_H=300.0,
    F_lim=10.0,
    K_ini=0.0,
    K_GP=0.5,
    K_GI=0.1,
    tau=1.25,
    tau_e=10 / 6,
    G_e=600.0,
    rho=200.0,
    M_b=1.0,
    k_F=0.5,
    k_c=0.5,
    eps_delta=1e-4,
)


def sigmoid(x):
    return 0.5 * (1 + math.tanh(0.5 * x))


def softplus(x):
    return max(x, 0.0) + math.log1p(math.exp(-abs(x)))


def command(scenario, robot, t):
    s = 1.0 if robot == 0 else -1.0
    if scenario == "paper":
        A = 10.0 * s
        return (
            A * (1 - math.cos(2 * math.pi * t)),
            A * 2 * math.pi * math.sin(2 * math.pi * t),
            A * (t - math.sin(2 * math.pi * t) / (2 * math.pi)),
        )
    v = a = x = 0.0
    for t0, A in ((0.0, 0.1 * s), (1.0, 0.5), (2.0, -0.2 * s)):
        u = t - t0
        if 0 <= u < 1:
            v += A * (1 - math.cos(2 * math.pi * u))
            a += A * 2 * math.pi * math.sin(2 * math.pi * u)
            x += A * (u - math.sin(2 * math.pi * u) / (2 * math.pi))
        elif u >= 1:
            x += A
    return v, a, x


def force(p, delta, delta_dot):
    kelvin = p["K_g"] * delta + p["R_g"] * delta_dot
    return p["k_c"] * softplus(kelvin / p["k_c"]) * sigmoid(delta / p["eps_delta"])


def robot_rates(p, s, yi, F, w, F_gain, v_cmd, a_cmd, x_ref):
    """The nine per-robot rates once the contact force F and the switch value w are fixed."""
    x_r, v_r, x_v, v_v, q_c, x_f, v_f, Z, Y_e = yi
    gamma = 1 - w * (p["K_ini"] + p["K_GP"] * (F_gain - p["F_lim"]) + p["K_GI"] * Z)
    dY = (1 - w) * (x_ref - x_r) - p["tau_e"] * Y_e - w * p["rho"] * Y_e
    v_ref = v_cmd + (1 - w) * p["G_e"] * Y_e
    a_ref = a_cmd + (1 - w) * p["G_e"] * dY
    g = (1 - gamma) * p["beta_H"]
    err = v_ref - v_r - g * v_f
    # Unknowns (e_c, a_r, a_f):
    #   e_c + M_c a_r + M_c g a_f = M_c a_ref + R_c err + K_c q_c
    #   -mu_H e_c + M_r a_r       = -s F
    #   -e_c + M_f a_f            = -(R_f v_f + K_f x_f)
    M = np.array([[1.0, p["M_c"], p["M_c"] * g], [-p["mu_H"], p["M_r"], 0.0], [-1.0, 0.0, p["M_f"]]])
    rhs_vec = np.array([p["M_c"] * a_ref + p["R_c"] * err + p["K_c"] * q_c, -s * F, -(p["R_f"] * v_f + p["K_f"] * x_f)])
    e_c, a_r, a_f = np.linalg.solve(M, rhs_vec)
    return np.array(
        [
            v_r,
            a_r,
            v_v,
            -p["mu_H"] * e_c / p["M_v"],
            err,
            v_f,
            a_f,
            w * (F - p["F_lim"]) - p["tau"] * Z - (1 - w) * p["rho"] * Z,
            dY,
        ]
    )


def rhs(t, y, scenario, p=TABLE1, switch="smooth"):
    # y: per robot [x_r, v_r, x_v, v_v, q_c, x_f, v_f, Z, Y_e] for L then R, then x_o, v_o.
    x_o, v_o = y[18], y[19]
    dy = np.zeros(20)
    forces = []
    for i, s in enumerate((1.0, -1.0)):
        yi = y[i * 9 : (i + 1) * 9]
        F = force(p, s * (yi[0] - x_o), s * (yi[1] - v_o))
        forces.append(F)
        w = sigmoid((F - p["F_lim"]) / p["k_F"])
        command_i = command(scenario, i, t)
        if switch == "smooth":
            dy[i * 9 : (i + 1) * 9] = robot_rates(p, s, yi, F, w, F, *command_i)
        else:  # blend: w-weighted mix of the switch-off and switch-on fields (on-field gamma at F >= F_lim)
            off = robot_rates(p, s, yi, F, 0.0, F, *command_i)
            on = robot_rates(p, s, yi, F, 1.0, max(F, p["F_lim"]), *command_i)
            dy[i * 9 : (i + 1) * 9] = (1 - w) * off + w * on
    dy[18] = v_o
    dy[19] = (forces[0] - forces[1]) / p["M_b"]
    return dy, forces


def to_coopjax_order(y):
    """Reference layout (robot-major) -> coopjax layout (quantity-major: x_r_L, x_r_R, ...)."""
    robot = np.asarray(y[:18]).reshape(2, 9).T.reshape(18)
    return np.concatenate([robot, y[18:]])

import os, time, numpy as np
os.environ["XLA_FLAGS"] = "--xla_cpu_use_fusion_emitters=false"
import jax, jax.numpy as jnp
import coopjax as cj
from coopjax import model
from coopjax.scenarios import Clock, SCENARIOS
from coopjax.integration import plain_rk4, filippov
B = 4096; n = 1000
rng = np.random.default_rng(0)
p = cj.make_params(M_b=np.exp(rng.uniform(np.log(0.5), np.log(5), B)), K_GP=rng.uniform(0.3, 0.7, B))
sc = SCENARIOS["carry"]; opt = model.Options()
def bench(name, f, *args):
    f(*args).block_until_ready()
    ts = []
    for _ in range(3):
        t = time.time(); f(*args).block_until_ready(); ts.append(time.time() - t)
    print(f"{name:40s} {B * n / np.median(ts) / 1e6:6.2f} M steps/s")
@jax.jit
def bare_rk4(p):
    def body(y, k):
        t = k.astype(y.dtype) * 1e-3
        y2, F, xr, _ = plain_rk4.step(p, y, t, 1e-3, sc, opt)
        return y2, None
    return jax.lax.scan(body, model.init_state(p), jnp.arange(n))[0]
@jax.jit
def bare_fil(p):
    def body(y, k):
        t = k.astype(y.dtype) * 1e-3
        y2, F, xr, _ = filippov.step(p, y, t, 1e-3, sc, opt)
        return y2, None
    return jax.lax.scan(body, model.init_state(p), jnp.arange(n))[0]
@jax.jit
def field4(p):
    def body(y, k):
        t = k.astype(y.dtype) * 1e-3
        d, aux = model.vector_field(p, y, Clock.at(t), sc, opt)
        return y + 1e-9 * d, None
    return jax.lax.scan(body, model.init_state(p), jnp.arange(4 * n))[0]
full = lambda integ: jax.jit(lambda p: cj.integration.integrate(p, cj.integration.SimConfig("carry", integrator=integ, T=1.0)).metrics.peak_grip)
#bench("integrate rk4 (metrics, divergence)", full("rk4"), p)
#bench("bare rk4 scan (no metrics)", bare_rk4, p)
#bench("4 field evaluations per step", field4, p)
#bench("integrate filippov", full("filippov"), p)
#bench("bare filippov scan", bare_fil, p)
#c = bare_rk4.lower(p).compile().cost_analysis()
#c = c[0] if isinstance(c, list) else c
#print("bare rk4 per sample-step: flops", c.get("flops", 0) / B / n, "bytes", c.get("bytes accessed", 0) / B / n)
cfg = lambda integ: cj.integration.SimConfig("carry", integrator=integ, T=1.0)
def blocked(integ, size):
    def f(p):
        blocks = jax.tree_util.tree_map(lambda x: jnp.moveaxis(x.reshape(x.shape[:-1] + (B // size, size)), -2, 0), p)
        out = jax.lax.map(lambda q: cj.integration.integrate(q, cfg(integ)).metrics.peak_grip, blocks)
        return out.reshape(-1)
    return jax.jit(f)
for size in (128, 256, 512, 1024):
    bench(f"integrate rk4 in blocks of {size}", blocked("rk4", size), p)
for size in (256, 1024):
    bench(f"integrate filippov in blocks of {size}", blocked("filippov", size), p)

import sys, time, os, glob
import jax, jax.numpy as jnp
sys.path.insert(0, os.getcwd())
import envs
from specguard_jax import ekf_kernel
from bench.autoreset_cost import timed
n = int(sys.argv[1]); mode = sys.argv[2]
out = os.environ.get("OUT", "/tmp")
for alias in (False, True):
  ekf_kernel.ALIAS_P = alias
  env = envs.make("drone", fused_ekf=True)
  st = jax.jit(jax.vmap(env.reset))(jax.random.split(jax.random.PRNGKey(0), n))
  act = jnp.zeros((n, env.action_size))
  if mode == "dump":
    f = jax.jit(lambda s: jax.vmap(env.step)(s, act))
    txt = f.lower(st).compile().as_text()
    open(f"{out}/hlo_alias{int(alias)}.txt", "w").write(txt)
    print("dumped", alias, len(txt), flush=True)
  else:
    print(f"alias={alias}: Vmap(env).step {timed(lambda s: jax.vmap(env.step)(s, act), st, 32):.3f} ms", flush=True)
